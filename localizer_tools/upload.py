"""Survey upload tool: sends a CSV or JSON survey file to a running server, in chunks.

    python -m localizer_tools.upload FILE --site ID [--key KEY] [--format csv|json|ujiindoorloc] [--dry-run]

It first validates every chunk with ``?dry_run=true`` and prints a per-row error report
(file line, field, message); only a clean file is then stored. Every chunk names the file
(``?source=<its SHA-256>``) and its first row, so the server stores each row of the file
once: re-running after a crash, with any ``--chunk-size``, stores exactly the rows still
missing. Each chunk also carries an ``Idempotency-Key`` naming the file and its rows, so a
retried chunk is answered as a replay.

A missing file or key, a server that does not answer, a refused key (401/403) or an
unknown site (404) is one ``error:`` line on stderr and exit status 1 (2 for usage).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import httpx
from tqdm import tqdm

RETRIES = 4


class Refused(Exception):
    """The server refused the key (401/403) or does not know the site (404): nothing to retry."""


def _detail(answer: httpx.Response) -> object:
    try:
        return answer.json().get("detail")
    except ValueError:
        return answer.text


def check(client: httpx.Client, site_id: int) -> None:
    """Fail fast, before any chunk: the server answers, takes the key and knows the site."""
    client.get("/healthz")
    answer = client.get(f"/api/v1/sites/{site_id}")
    if answer.status_code in (401, 403, 404):
        where = client.base_url
        raise Refused({401: f"{where} refused the key (401: {_detail(answer)})",
                       403: f"{where}: the key may not upload surveys, an admin key is needed (403: {_detail(answer)})",
                       404: f"{where}: {_detail(answer)} (404)"}[answer.status_code])


@dataclass
class Chunk:
    index: int
    body: bytes
    content_type: str
    rows: int
    first_row: int
    lines: list[int] | None  # file line of each data row (CSV formats)


def chunks_of(path: Path, fmt: str, size: int) -> Iterator[Chunk]:
    """Split the file into self-contained request bodies of at most ``size`` rows."""
    if fmt == "json":
        doc = json.loads(path.read_bytes())
        rows = doc["fingerprints"] if isinstance(doc, dict) else doc
        for index, start in enumerate(range(0, len(rows), size)):
            part = rows[start : start + size]
            body = json.dumps({"fingerprints": part}).encode()
            yield Chunk(index, body, "application/json", len(part), start, None)
        return
    with path.open(newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        header = next(reader)
        batch: list[list[str]] = []
        lines: list[int] = []
        index = first = 0
        for row in reader:
            batch.append(row)
            lines.append(reader.line_num)
            if len(batch) == size:
                yield _csv_chunk(index, header, batch, first, lines)
                index, first, batch, lines = index + 1, first + len(batch), [], []
        if batch:
            yield _csv_chunk(index, header, batch, first, lines)


def _csv_chunk(index: int, header: list[str], rows: list[list[str]], first: int, lines: list[int]) -> Chunk:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return Chunk(index, out.getvalue().encode(), "text/csv", len(rows), first, lines)


class Uploader:
    def __init__(self, client: httpx.Client, site_id: int, fmt: str, file_hash: str):
        self.client = client
        self.url = f"/api/v1/sites/{site_id}/surveys"
        self.params: dict[str, str] = {"format": fmt} if fmt == "ujiindoorloc" else {}
        self.params["source"] = f"sha256:{file_hash}"
        self.file_hash = file_hash

    def send(self, chunk: Chunk, dry_run: bool) -> httpx.Response:
        """POST one chunk; transport errors, 5xx and 429 are retried with the same idempotency key."""
        headers = {"Content-Type": chunk.content_type}
        if not dry_run:
            headers["Idempotency-Key"] = f"upload:{self.file_hash[:20]}:{chunk.first_row}+{chunk.rows}"
        params = {**self.params, "first_row": str(chunk.first_row)}
        if dry_run:
            params["dry_run"] = "true"
        for attempt in range(RETRIES):
            try:
                answer = self.client.post(self.url, content=chunk.body, headers=headers, params=params)
                if answer.status_code < 500 and answer.status_code != 429:
                    return answer
            except httpx.TransportError:
                if attempt == RETRIES - 1:
                    raise
            time.sleep(0.5 * 2**attempt)
        return answer


def describe_errors(chunk: Chunk, answer: httpx.Response) -> list[str]:
    """One line per error, with the row's position in the whole file."""
    detail = _detail(answer)
    if not isinstance(detail, list):
        return [f"chunk {chunk.index}: HTTP {answer.status_code}: {detail}"]
    report = []
    for err in detail:
        row = err.get("row")
        where = "file"
        if row is not None:
            where = f"row {chunk.first_row + row}"
            if chunk.lines is not None and row < len(chunk.lines):
                where += f" (line {chunk.lines[row]})"
        elif chunk.lines is not None and err.get("line") == 1:
            where = "header (line 1)"
        field = f" {err['field']}:" if err.get("field") else ""
        report.append(f"{where}:{field} {err.get('msg', err)}")
    return report


def upload(
    path: Path, base_url: str, key: str, site_id: int, fmt: str, chunk_size: int = 2000,
    dry_run: bool = False, validate_first: bool = True, progress: bool = True, out=sys.stdout,
) -> int:
    """Validate (and unless ``dry_run``, store) a survey file; returns a process exit code."""
    content = path.read_bytes()
    file_hash = hashlib.sha256(content).hexdigest()
    rows = None if fmt == "json" else max(content.count(b"\n") - 1, 0)
    totals = {"accepted": 0, "skipped": 0, "new_reference_points": 0, "already_stored": 0, "replayed_chunks": 0}
    started = time.perf_counter()
    with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {key}"}, timeout=300) as client:
        check(client, site_id)
        uploader = Uploader(client, site_id, fmt, file_hash)
        passes = ([True] if dry_run or validate_first else []) + ([] if dry_run else [False])
        for is_dry in passes:
            errors: list[str] = []
            label = "validating" if is_dry else "uploading"
            with tqdm(desc=label, unit="row", total=rows, disable=not progress, file=sys.stderr) as bar:
                for chunk in chunks_of(path, fmt, chunk_size):
                    answer = uploader.send(chunk, dry_run=is_dry)
                    if answer.status_code >= 400:
                        errors += describe_errors(chunk, answer)
                        if not is_dry:
                            break  # stop at the first refused chunk: earlier ones are stored, keys make a re-run safe
                    elif answer.headers.get("Idempotent-Replay"):
                        totals["replayed_chunks"] += 1
                    elif not is_dry:
                        for name in ("accepted", "skipped", "new_reference_points", "already_stored"):
                            totals[name] += answer.json().get(name, 0)
                    bar.update(chunk.rows)
            if errors:
                print(f"{len(errors)} problem(s); nothing {'was' if is_dry else 'more was'} stored:", file=out)
                for line in errors:
                    print("  " + line, file=out)
                return 1
    seconds = time.perf_counter() - started
    if dry_run:
        print(f"{path.name}: valid, nothing stored ({seconds:.1f} s)", file=out)
    else:
        print(
            f"{path.name}: {totals['accepted']} fingerprints stored, {totals['skipped']} skipped, "
            f"{totals['new_reference_points']} new reference points in {seconds:.1f} s"
            + (f"; {totals['replayed_chunks']} chunk(s) had been stored before" if totals["replayed_chunks"] else "")
            + (f"; {totals['already_stored']} row(s) had been stored by an earlier run" if totals["already_stored"] else ""),
            file=out,
        )
    return 0


def guess_format(path: Path) -> str:
    if path.suffix.lower() == ".json":
        return "json"
    with path.open(encoding="utf-8-sig") as f:
        header = f.readline()
    return "ujiindoorloc" if header.startswith("WAP001") or "LONGITUDE" in header else "csv"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends ``(default: X)`` to an option's help unless X is None/False or the help names it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is False or "default" in text:
            return text
        return super()._get_help_string(action) or text


def _version() -> str:
    try:
        return version("localizer")
    except PackageNotFoundError:
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m localizer_tools.upload", description=__doc__.split("\n\n")[0],
                                     formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    parser.add_argument("file", type=Path, help="survey file: CSV, JSON ({fingerprints: [...]}) or UJIIndoorLoc CSV")
    parser.add_argument("--site", type=int, required=True, help="site id")
    parser.add_argument("--url", default=os.environ.get("LOCALIZER_URL", "http://127.0.0.1:8000"),
                        help="server base URL (env LOCALIZER_URL)")
    parser.add_argument("--key", help="admin key (default: env LOCALIZER_ADMIN_KEY, else LOCALIZER_API_KEY)",
                        default=os.environ.get("LOCALIZER_ADMIN_KEY") or os.environ.get("LOCALIZER_API_KEY"))
    parser.add_argument("--format", choices=["csv", "json", "ujiindoorloc"], help="default: from the file")
    parser.add_argument("--chunk-size", type=int, default=2000, help="rows per request")
    parser.add_argument("--dry-run", action="store_true", help="validate every row; store nothing")
    parser.add_argument("--no-validate", action="store_true", help="skip the validation pass before storing")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if not args.key:
        return _fail("an admin key is needed: pass --key or set LOCALIZER_ADMIN_KEY (or LOCALIZER_API_KEY)", 2)
    if not args.file.is_file():
        return _fail(f"{args.file}: no such file", 2)
    if args.chunk_size < 1:
        return _fail(f"--chunk-size must be at least 1 row, not {args.chunk_size}", 2)
    try:
        return upload(
            args.file, args.url, args.key, args.site, args.format or guess_format(args.file), args.chunk_size,
            dry_run=args.dry_run, validate_first=not args.no_validate, progress=not args.quiet,
        )
    except Refused as exc:
        return _fail(str(exc))
    except httpx.ConnectError as exc:
        return _fail(f"cannot connect to {args.url}: is the server running? ({exc})")
    except httpx.HTTPError as exc:
        return _fail(f"{args.url}: {type(exc).__name__}: {exc}")


def _fail(message: str, code: int = 1) -> int:
    print(f"error: {message}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
