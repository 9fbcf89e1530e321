"""Fetch a registry model into the cache: resumable HTTP download, size + hash check, atomic install.

Only ``python -m engine models fetch`` (and the add-on's Download button, which runs it)
calls :func:`fetch`; nothing downloads implicitly. The download goes to
``<cache>/<name>/.<file>.part``; an interrupted or stalled transfer keeps the part and the
next fetch resumes it with an HTTP ``Range`` request (a server that ignores ranges
restarts it). Only a file whose size and SHA-256 match the registry is moved into place
(``os.replace``); a wrong one is deleted. Every failure is one :class:`DownloadError`
line naming the model or URL and the fix.
"""

from __future__ import annotations

import errno
import shutil
import socket
import time
import urllib.error
import urllib.request
from http.client import HTTPException
from pathlib import Path

from .. import __version__
from ..errors import Cancelled, InputError
from .registry import ENGINE_ROOT, ModelSpec
from .store import ModelStore, sha256_file

CHUNK = 1 << 16
#: Seconds without a byte before a transfer counts as stalled (the part is kept).
DEFAULT_TIMEOUT = 30.0


class DownloadError(InputError):
    """A fetch failed; the message names the model/URL, the fix says what to do."""


def _open(url: str, start: int, timeout: float):
    headers = {"User-Agent": f"motion-splats/{__version__}"}
    if start:
        headers["Range"] = f"bytes={start}-"
    return urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout)  # noqa: S310


def _resume_offset(resp, start: int) -> int:
    """Where the response body starts in the file: ``start`` for a matching 206, else 0."""
    if start and resp.status == 206:
        rng = resp.headers.get("Content-Range", "")  # "bytes 100-999/1000"
        try:
            first = int(rng.split()[1].split("-")[0])
        except (IndexError, ValueError):
            return 0
        return start if first == start else 0
    return 0


def _expected_total(resp, offset: int, spec: ModelSpec) -> int | None:
    length = resp.headers.get("Content-Length")
    if length is not None and length.isdigit():
        return offset + int(length)
    return spec.bytes


def _transfer(spec: ModelSpec, url: str, part: Path, timeout: float, reporter) -> None:
    """Append the body of ``url`` to ``part`` (resuming what is there). Raises DownloadError."""
    start = part.stat().st_size if part.is_file() else 0
    if spec.bytes is not None and start >= spec.bytes:
        return  # complete already; the checks decide
    try:
        resp = _open(url, start, timeout)
    except urllib.error.HTTPError as exc:
        if exc.code == 416 and start:  # range past the end: the part may be whole; let the checks decide
            return
        raise DownloadError(f"HTTP {exc.code} {exc.reason} downloading {spec.name}", url,
                            "the file may have moved: try again later, or download it yourself and pass it "
                            f"with --{spec.role}-model PATH") from exc
    except (urllib.error.URLError, OSError, HTTPException) as exc:
        reason = getattr(exc, "reason", exc)
        raise DownloadError(f"cannot reach the server for {spec.name} ({reason})", url,
                            "check the internet connection (or proxy) and run the fetch again") from exc
    with resp:
        offset = _resume_offset(resp, start)
        total = _expected_total(resp, offset, spec)
        done, last = offset, 0.0
        stage = f"download {spec.name}"
        try:
            with open(part, "r+b" if offset and part.exists() else "wb") as fh:
                fh.seek(offset)
                fh.truncate()
                while True:
                    block = resp.read1(CHUNK)  # what has arrived: a stall keeps every byte so far
                    if not block:
                        break
                    fh.write(block)
                    done += len(block)
                    now = time.monotonic()
                    if reporter is not None and now - last > 0.2:
                        reporter.progress(stage, done, total, mb=done / 1e6)
                        last = now
        except OSError as exc:
            if exc.errno == errno.ENOSPC:
                part.unlink(missing_ok=True)
                raise DownloadError(f"disk full while downloading {spec.name}", part.parent,
                                    f"free some space or move the cache with the MOTION_SPLATS_MODELS "
                                    f"environment variable, then fetch again") from exc
            if isinstance(exc, (socket.timeout, TimeoutError)):
                raise DownloadError(f"download of {spec.name} stalled (no data for {timeout:g} s) after "
                                    f"{done} bytes", url, "run the fetch again: it resumes where it stopped") from exc
            raise DownloadError(f"download of {spec.name} interrupted after {done} bytes ({exc})", url,
                                "run the fetch again: it resumes where it stopped") from exc
        except HTTPException as exc:  # IncompleteRead and friends: the connection dropped
            raise DownloadError(f"download of {spec.name} interrupted after {done} bytes ({type(exc).__name__})",
                                url, "run the fetch again: it resumes where it stopped") from exc
        if reporter is not None:
            reporter.progress(stage, done, total or done, mb=done / 1e6)
        if total is not None and done < total:
            raise DownloadError(f"download of {spec.name} interrupted after {done} of {total} bytes", url,
                                "run the fetch again: it resumes where it stopped")


def _check(spec: ModelSpec, part: Path, url: str) -> str:
    """Size and hash of a finished part against the registry; a wrong file is deleted."""
    size = part.stat().st_size
    if spec.bytes is not None and size != spec.bytes:
        part.unlink(missing_ok=True)
        raise DownloadError(f"{spec.name}: downloaded {size} bytes, expected {spec.bytes}; the file was deleted",
                            url, "fetch again; if it persists the file on the server changed")
    digest = sha256_file(part)
    if spec.sha256 is not None and digest != spec.sha256:
        part.unlink(missing_ok=True)
        raise DownloadError(f"{spec.name}: SHA-256 {digest[:16]}… does not match the registry's "
                            f"{spec.sha256[:16]}…; the file was deleted", url,
                            "fetch again; if it persists the file on the server changed (do not use it)")
    return digest


def _install(store: ModelStore, spec: ModelSpec, part: Path, digest: str, source: str | None) -> Path:
    try:
        return store.install(spec, part, digest, source)
    except OSError as exc:
        part.unlink(missing_ok=True)
        raise DownloadError(f"cannot move {spec.name} into place ({exc.strerror or exc})", store.folder(spec),
                            "free some space or make the model cache writable, then fetch again") from exc


def fetch(spec: ModelSpec, store: ModelStore | None = None, reporter=None, timeout: float = DEFAULT_TIMEOUT,
          urls=None) -> dict:
    """Install ``spec`` into ``store``: copy the shipped file or download it (resuming), check, move in place.

    Parameters
    ----------
    spec : the registry entry.
    store : the cache (default folder when None).
    reporter : engine.protocol.Reporter for progress (bytes), optional.
    timeout : seconds without data before a transfer is abandoned (the part is kept).
    urls : override the registry URLs (tests, mirrors).

    Returns
    -------
    dict with ``name``, ``path``, ``sha256``, ``bytes``, ``source`` (URL or shipped path),
    ``already`` (True when it was installed and nothing was done).
    """
    store = store or ModelStore()
    st = store.state(spec)
    if st.status == "installed":
        return {"name": spec.name, "path": str(st.path), "sha256": st.sha256, "bytes": st.bytes,
                "source": None, "already": True}
    folder, part = store.folder(spec), store.part_path(spec)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DownloadError(f"cannot create the model cache ({exc.strerror or exc})", folder,
                            "set MOTION_SPLATS_MODELS to a writable folder") from exc
    shipped = spec.shipped_path
    if shipped is not None:
        try:
            shutil.copyfile(shipped, part)
        except OSError as exc:
            part.unlink(missing_ok=True)
            raise DownloadError(f"cannot copy the shipped {spec.name} ({exc.strerror or exc})", folder,
                                "free some space or set MOTION_SPLATS_MODELS to another folder") from exc
        digest = _check(spec, part, str(shipped))
        path = _install(store, spec, part, digest, None)
        return {"name": spec.name, "path": str(path), "sha256": digest, "bytes": path.stat().st_size,
                "source": str(shipped), "already": False}
    urls = list(urls if urls is not None else spec.urls)
    if not urls and spec.shipped:
        raise DownloadError(f"{spec.name} should ship with the engine but its file is missing",
                            ENGINE_ROOT / spec.shipped, "reinstall the add-on (or the engine checkout)")
    if not urls:
        raise DownloadError(f"{spec.name} has no published download in the engine's ONNX contract", None,
                            spec.note or f"export the model to ONNX yourself and pass --{spec.role}-model PATH")
    failure = None
    for url in urls:  # mirrors in order; a reachable one that fails mid-way stops here (resume it later)
        try:
            _transfer(spec, url, part, timeout, reporter)
            digest = _check(spec, part, url)
        except KeyboardInterrupt:
            kept = part.stat().st_size if part.is_file() else 0
            raise Cancelled(f"download of {spec.name} interrupted; {kept} bytes kept, run the fetch again to "
                            "resume") from None
        except DownloadError as exc:
            failure = exc
            if "cannot reach" in exc.problem or exc.problem.startswith("HTTP "):
                continue
            raise
        path = _install(store, spec, part, digest, url)
        return {"name": spec.name, "path": str(path), "sha256": digest, "bytes": path.stat().st_size,
                "source": url, "already": False}
    raise failure
