"""Async HTTP client for the localizer API (API.md v1), built on httpx.

Only what API.md fixes is used: base ``/api/v1``, ``Authorization: Bearer <key>``,
JSON bodies. One :class:`LocalizerClient` can carry hundreds of concurrent phones
(httpx pools the connections).
"""

from __future__ import annotations

import asyncio
from typing import Any

import httpx

API = "/api/v1"


class ApiError(Exception):
    """A non-success answer; ``detail`` is the server's ``{"detail": ...}`` if any."""

    def __init__(self, status: int, detail: Any, method: str, path: str, key_name: str = "key"):
        super().__init__(f"{method} {path} -> {status}: {detail}")
        self.status, self.detail, self.key_name = status, detail, key_name


def _retryable(exc: Exception) -> bool:
    if isinstance(exc, httpx.TransportError):
        return True
    return isinstance(exc, ApiError) and (exc.status >= 500 or exc.status == 429)


class LocalizerClient:
    def __init__(self, base_url: str, api_key: str, *, transport: httpx.AsyncBaseTransport | None = None,
                 timeout: float = 30.0, max_connections: int = 200, key_name: str = "key"):
        self.key_name = key_name  # "admin key" / "device key", named in errors
        self.http = httpx.AsyncClient(
            base_url=base_url.rstrip("/"), transport=transport, timeout=timeout,
            headers={"Authorization": f"Bearer {api_key}"},
            limits=httpx.Limits(max_connections=max_connections, max_keepalive_connections=max_connections),
        )

    async def __aenter__(self) -> LocalizerClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()

    async def aclose(self) -> None:
        await self.http.aclose()

    async def request(self, method: str, path: str, json: Any = None, params: dict | None = None) -> Any:
        r = await self.http.request(method, path, json=json, params=params)
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail")
            except Exception:
                detail = r.text
            raise ApiError(r.status_code, detail, method, path, self.key_name)
        return None if r.status_code == 204 or not r.content else r.json()

    async def with_retries(self, method: str, path: str, json: Any = None, retries: int = 4,
                           backoff_s: float = 0.2) -> Any:
        """Repeat an idempotent request on transport errors, 5xx and 429."""
        for attempt in range(retries + 1):
            try:
                return await self.request(method, path, json)
            except Exception as exc:  # noqa: BLE001 - filtered below
                if attempt == retries or not _retryable(exc):
                    raise
                await asyncio.sleep(backoff_s * 2 ** attempt)

    # --- service
    async def health(self) -> dict:
        return await self.request("GET", "/healthz")

    async def check(self, site_id: int | None = None, admin: bool = False) -> None:
        """Fail fast with the server's own answer: nothing listening, a refused key, an unknown site.

        Admin: ``GET`` the site (or the site list). Device: ``locate`` one made-up scan on the
        site (``409``/``422`` mean the site exists), else list the key's sessions."""
        await self.health()
        if admin:
            await self.request("GET", f"{API}/sites" + (f"/{site_id}" if site_id is not None else ""))
        elif site_id is None:
            await self.request("GET", f"{API}/sessions", params={"limit": 1})
        else:
            try:
                await self.locate(site_id, {"wifi:preflight": -60.0})
            except ApiError as exc:
                if exc.status not in (409, 422):
                    raise

    # --- sites (admin)
    async def list_sites(self) -> list[dict]:
        return await self.request("GET", f"{API}/sites")

    async def create_site(self, payload: dict) -> dict:
        return await self.request("POST", f"{API}/sites", payload)

    async def get_site(self, site_id) -> dict:
        return await self.request("GET", f"{API}/sites/{site_id}")

    async def update_site_settings(self, site_id, settings: dict) -> dict:
        return await self.request("PATCH", f"/api/v1/sites/{site_id}", {"settings": settings})

    async def upload_survey(self, site_id, fingerprints: list[dict]) -> dict:
        return await self.request("POST", f"{API}/sites/{site_id}/surveys", {"fingerprints": fingerprints})

    async def train_model(self, site_id, algorithm: str, params: dict | None = None,
                          use_heading: bool | None = None, kinds: list[str] | None = None) -> dict:
        body: dict[str, Any] = {"algorithm": algorithm}
        if params:
            body["params"] = params
        if use_heading is not None:
            body["use_heading"] = use_heading
        if kinds:
            body["kinds"] = kinds
        return await self.request("POST", f"{API}/sites/{site_id}/models", body)

    async def list_models(self, site_id) -> list[dict]:
        return await self.request("GET", f"{API}/sites/{site_id}/models")

    async def get_model(self, site_id, model_id) -> dict:
        return await self.request("GET", f"{API}/sites/{site_id}/models/{model_id}")

    async def activate_model(self, site_id, model_id) -> dict:
        return await self.request("POST", f"{API}/sites/{site_id}/models/{model_id}/activate")

    async def wait_model(self, site_id, model_id, timeout_s: float = 300.0, poll_s: float = 0.5) -> dict:
        """Poll a model until it is ``ready`` or ``failed`` (or the timeout passes)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            model = await self.get_model(site_id, model_id)
            if model.get("status") in ("ready", "failed") or loop.time() > deadline:
                return model
            await asyncio.sleep(poll_s)

    # --- device
    async def locate(self, site_id, rss: dict[str, float], heading_deg: float | None = None) -> dict:
        body: dict[str, Any] = {"rss": rss}
        if heading_deg is not None:
            body["heading_deg"] = heading_deg
        return await self.request("POST", f"{API}/sites/{site_id}/locate", body)

    async def open_session(self, site_id, filter: str, initial: dict | None = None, model_id=None,
                           seed: int | None = None, filter_params: dict[str, float] | None = None) -> dict:
        """A new session; ``seed`` (an extension) fixes its tracker's random draws, ``filter_params``
        (an extension) override its tracker's defaults."""
        body: dict[str, Any] = {"site_id": site_id, "filter": filter}
        if initial is not None:
            body["initial"] = initial
        if model_id is not None:
            body["model_id"] = model_id
        if seed is not None:
            body["seed"] = seed
        if filter_params:
            body["filter_params"] = filter_params
        return await self.request("POST", f"{API}/sessions", body)

    async def post_batch(self, session_id, batch: dict, retries: int = 4) -> dict:
        """Post one batch; a failed post is retried with the same ``seq`` (the server dedups)."""
        return await self.with_retries("POST", f"{API}/sessions/{session_id}/batches", batch, retries)

    async def get_track(self, session_id, smoothed: bool = False, smoother: str = "rts") -> list[dict]:
        """The session's track (``smoothed``: the fixed-interval smoother's, ``smoother`` which one; extensions)."""
        query = ("?smoothed=true" + ("" if smoother == "rts" else f"&smoother={smoother}")) if smoothed else ""
        return await self.with_retries("GET", f"{API}/sessions/{session_id}/track{query}")

    async def close_session(self, session_id) -> None:
        await self.request("DELETE", f"{API}/sessions/{session_id}")
