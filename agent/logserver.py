"""Ground-station log download: a read-only, token-authenticated HTTP API over recorded flights.

Routes (all GET/HEAD; everything but health needs ``Authorization: Bearer TOKEN``)::

    /api/health                       liveness, no token
    /api/status                       the daemon's status (a callable supplies it)
    /api/flights                      flights under the storage root: id, size, times, frames
    /api/flights/{id}                 one flight: details and its file list
    /api/flights/{id}/archive         the whole flight as a tar, streamed (no copy in memory/disk)
    /api/flights/{id}/files/{path}    one file, with HTTP Range for resumed downloads

Safety: a flight id is a plain directory name directly under the root; a file path must stay
inside its flight after resolution, and no component may be a symlink, so ``..``, absolute
paths, encoded dots and links out of the tree all answer 404. Files are read in a thread pool and
sent in chunks, so downloads do not block the event loop (capture runs in its own process).
The token file must not be readable by group or others (0600), like an SSH key.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import os
import re
import stat
import tarfile
import threading
from collections.abc import Callable
from pathlib import Path

from aiohttp import web

log = logging.getLogger(__name__)

_FLIGHT_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_CHUNK = 256 * 1024


class TokenFileError(ValueError):
    """The token file is missing, empty or readable by others."""


def load_token(path: str | Path) -> str:
    """Read the bearer token; refuse a file that group or others can read or write."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise TokenFileError(f"{path}: token file not found") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise TokenFileError(f"{path}: token file must be private (chmod 600), mode is "
                             f"{stat.S_IMODE(st.st_mode):o}")
    token = path.read_text().strip()
    if len(token) < 16:
        raise TokenFileError(f"{path}: token must be at least 16 characters")
    return token


def _flight_dir(root: Path, flight_id: str) -> Path:
    if not _FLIGHT_ID.match(flight_id) or flight_id in (".", ".."):
        raise web.HTTPNotFound(text="no such flight")
    d = root / flight_id
    if d.is_symlink() or not d.is_dir():
        raise web.HTTPNotFound(text="no such flight")
    return d


def _safe_file(flight: Path, rel: str) -> Path:
    """The file ``rel`` inside ``flight``, or 404 for anything that could escape it."""
    if not rel or rel.startswith(("/", "\\")) or "\x00" in rel or "\\" in rel:
        raise web.HTTPNotFound(text="no such file")
    parts = rel.split("/")
    if any(p in ("", ".", "..") for p in parts):
        raise web.HTTPNotFound(text="no such file")
    current = flight
    for p in parts:
        current = current / p
        if current.is_symlink():
            raise web.HTTPNotFound(text="no such file")
    try:
        resolved = current.resolve(strict=True)
    except (FileNotFoundError, RuntimeError):
        raise web.HTTPNotFound(text="no such file") from None
    if not resolved.is_relative_to(flight.resolve()) or not resolved.is_file():
        raise web.HTTPNotFound(text="no such file")
    return resolved


def _walk_files(flight: Path) -> list[tuple[str, Path, int, float]]:
    """(relative path, path, size, mtime) of regular files, symlinks skipped, sorted."""
    out = []
    for dirpath, dirnames, filenames in os.walk(flight, followlinks=False):
        base = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames if not (base / d).is_symlink())
        for name in sorted(filenames):
            p = base / name
            if p.is_symlink():
                continue
            try:
                st = p.stat()
            except FileNotFoundError:  # removed while listing
                continue
            if stat.S_ISREG(st.st_mode):
                out.append((p.relative_to(flight).as_posix(), p, st.st_size, st.st_mtime))
    return out


def _frame_times(flight: Path) -> tuple[int | None, int | None, int]:
    """First and last capture time (unix µs) and frame count from frames.csv, if readable."""
    csv = flight / "frames.csv"
    first = last = None
    n = 0
    try:
        with open(csv) as fh:
            next(fh, None)
            for line in fh:
                parts = line.strip().split(",")
                if len(parts) != 2:
                    continue
                try:
                    t = int(parts[1])
                except ValueError:
                    continue
                first = t if first is None else first
                last = t
                n += 1
    except OSError:
        pass
    return first, last, n


def _flight_summary(flight: Path) -> dict:
    files = _walk_files(flight)
    first, last, n = _frame_times(flight)
    return {"id": flight.name, "size_bytes": sum(f[2] for f in files), "files": len(files),
            "frames": n, "start_unix_us": first, "end_unix_us": last,
            "modified_unix": max((f[3] for f in files), default=flight.stat().st_mtime)}


class LogServer:
    """The aiohttp application over ``storage_root``; run with :meth:`start_in_thread` or aiohttp."""

    def __init__(self, storage_root: str | Path, token: str,
                 status: Callable[[], dict] | None = None,
                 request_processing: Callable[[Path], tuple[int, dict]] | None = None):
        """``request_processing(flight_dir)`` → (HTTP status, JSON body) queues a flight for processing;
        without it the API has no POST route at all."""
        self.root = Path(storage_root)
        self.token = token
        self.status = status or (lambda: {"state": "unknown"})
        self.request_processing = request_processing
        self.app = web.Application(middlewares=[self._auth])
        self.app.add_routes([
            web.get("/api/health", self.health),
            web.get("/api/status", self.get_status),
            web.get("/api/flights", self.list_flights),
            web.get("/api/flights/{flight}", self.flight_details),
            web.get("/api/flights/{flight}/archive", self.archive),
            web.get("/api/flights/{flight}/files/{path:.+}", self.file),
        ])
        if request_processing is not None:
            # the one non-GET route: it queues work and never touches the flight's files
            self.app.add_routes([web.post("/api/flights/{flight}/process", self.process)])
        self._runner: web.AppRunner | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.port: int | None = None

    @web.middleware
    async def _auth(self, request: web.Request, handler):
        if request.path == "/api/health":
            return await handler(request)
        header = request.headers.get("Authorization", "")
        scheme, _, given = header.partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(given.strip().encode(), self.token.encode()):
            raise web.HTTPUnauthorized(text="bearer token required",
                                       headers={"WWW-Authenticate": 'Bearer realm="uavsim"'})
        return await handler(request)

    async def health(self, request):
        return web.json_response({"status": "ok"})

    async def get_status(self, request):
        return web.json_response(self.status())

    async def list_flights(self, request):
        loop = asyncio.get_running_loop()

        def collect():
            if not self.root.is_dir():
                return []
            return [_flight_summary(d) for d in sorted(self.root.iterdir())
                    if d.is_dir() and not d.is_symlink() and _FLIGHT_ID.match(d.name)]

        return web.json_response({"flights": await loop.run_in_executor(None, collect)})

    async def flight_details(self, request):
        flight = _flight_dir(self.root, request.match_info["flight"])
        loop = asyncio.get_running_loop()

        def collect():
            summary = _flight_summary(flight)
            summary["file_list"] = [{"path": rel, "size_bytes": size} for rel, _, size, _ in _walk_files(flight)]
            return summary

        return web.json_response(await loop.run_in_executor(None, collect))

    async def process(self, request):
        flight = _flight_dir(self.root, request.match_info["flight"])
        status, body = self.request_processing(flight)
        return web.json_response(body, status=status)

    async def file(self, request):
        flight = _flight_dir(self.root, request.match_info["flight"])
        path = _safe_file(flight, request.match_info["path"])
        return web.FileResponse(path, chunk_size=_CHUNK)  # handles Range and HEAD

    async def archive(self, request):
        flight = _flight_dir(self.root, request.match_info["flight"])
        loop = asyncio.get_running_loop()
        files = await loop.run_in_executor(None, _walk_files, flight)
        resp = web.StreamResponse(headers={
            "Content-Type": "application/x-tar",
            "Content-Disposition": f'attachment; filename="{flight.name}.tar"'})
        await resp.prepare(request)
        for rel, path, _, mtime in files:
            try:
                fh = open(path, "rb")
            except FileNotFoundError:
                continue
            with fh:
                # Size at this moment: a file still being appended (telemetry.tlog) is cut here.
                size = os.fstat(fh.fileno()).st_size
                info = tarfile.TarInfo(f"{flight.name}/{rel}")
                info.size, info.mtime, info.mode = size, int(mtime), 0o644
                await resp.write(info.tobuf(format=tarfile.PAX_FORMAT))
                left = size
                while left > 0:
                    chunk = await loop.run_in_executor(None, fh.read, min(_CHUNK, left))
                    if not chunk:  # shrank underneath us: pad with zeros to keep the tar valid
                        chunk = bytes(min(_CHUNK, left))
                    await resp.write(chunk)
                    left -= len(chunk)
                if size % tarfile.BLOCKSIZE:
                    await resp.write(bytes(tarfile.BLOCKSIZE - size % tarfile.BLOCKSIZE))
        await resp.write(bytes(2 * tarfile.BLOCKSIZE))
        await resp.write_eof()
        return resp

    # ---- running ------------------------------------------------------------------------
    def start_in_thread(self, host: str = "127.0.0.1", port: int = 0) -> int:
        """Serve from a background thread with its own event loop; returns the bound port."""
        ready = threading.Event()
        errors: list[BaseException] = []

        def run():
            loop = asyncio.new_event_loop()
            self._loop = loop
            asyncio.set_event_loop(loop)
            try:
                self._runner = web.AppRunner(self.app, access_log=None)
                loop.run_until_complete(self._runner.setup())
                site = web.TCPSite(self._runner, host, port)
                loop.run_until_complete(site.start())
                self.port = site._server.sockets[0].getsockname()[1]
            except BaseException as exc:  # noqa: BLE001 - reported to the caller below
                errors.append(exc)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self._runner.cleanup())
            loop.close()

        self._thread = threading.Thread(target=run, name="logserver", daemon=True)
        self._thread.start()
        ready.wait(10.0)
        if errors:
            raise errors[0]
        log.info("log server listening on %s:%d", host, self.port)
        return self.port

    def stop(self) -> None:
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(10.0)
