# The localizer service image: runs from the source tree so migrations/ ships beside server/.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /app
COPY pyproject.toml README.md alembic.ini ./
COPY server ./server
COPY client_sim ./client_sim
COPY migrations ./migrations
RUN pip install -e ".[postgres]"

EXPOSE 8000
HEALTHCHECK --interval=10s --timeout=3s CMD python -c "import urllib.request; urllib.request.urlopen('http://127.0.0.1:8000/healthz')"
CMD ["python", "-m", "server", "serve", "--host", "0.0.0.0", "--port", "8000"]
