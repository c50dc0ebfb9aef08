"""The weights cache: its folder, offline mode, and fetching a file once with its sha256 checked.

A file is named by its ``source`` (a local path or a URL), its full ``sha256`` and a ``label`` for
messages (the weights' name). This module knows nothing of the registry, so that the registry (and
the loaders above it) import it, never the reverse.

The cache folder is ``$AAUTE_CACHE/weights`` (the features live beside it in ``$AAUTE_CACHE``), or
``~/.cache/aaute/weights``. Files named by a URL are downloaded there once, checked against their
sha256 and renamed into place only when complete. In offline mode (``offline=True`` or
``AAUTE_OFFLINE=1``) nothing touches the network: a file that is not cached is an error saying which
file is needed and where to put it.
"""

from __future__ import annotations

import hashlib
import logging
import os
import urllib.parse
import urllib.request
from pathlib import Path

from datamodules.atomic import atomic_write
from zoo.weights.files import CheckpointError, file_sha256

log = logging.getLogger("zoo.weights")  #: one logger for the whole package (its messages name zoo.weights)

URL_SCHEMES = ("http", "https", "file")


class WeightsError(CheckpointError):
    """Weights that cannot be found, fetched or trusted (the message says what to do)."""


def weights_dir() -> Path:
    """``$AAUTE_CACHE/weights`` or ``~/.cache/aaute/weights``."""
    root = os.environ.get("AAUTE_CACHE")
    return Path(root) / "weights" if root else Path.home() / ".cache" / "aaute" / "weights"


def offline_mode(offline: bool | None = None) -> bool:
    """``offline`` if given, else whether ``$AAUTE_OFFLINE`` is set to 1 / true / yes."""
    if offline is not None:
        return offline
    return os.environ.get("AAUTE_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def is_url(source: str) -> bool:
    """Whether ``source`` is a URL to download (http, https, file) rather than a local path."""
    return urllib.parse.urlparse(source).scheme in URL_SCHEMES


def _download(url: str, target: Path, sha256: str) -> None:
    """Fetch ``url`` into ``target`` atomically; a wrong sha256 leaves nothing behind."""
    log.info("downloading %s to %s", url, target)
    with atomic_write(target) as tmp:
        digest = hashlib.sha256()
        with urllib.request.urlopen(url, timeout=60) as response, open(tmp, "wb") as out:  # noqa: S310 (scheme checked)
            for block in iter(lambda: response.read(1 << 20), b""):
                digest.update(block)
                out.write(block)
        if digest.hexdigest() != sha256:
            raise WeightsError(f"{url}: downloaded file has sha256 {digest.hexdigest()}, the registry expects "
                               f"{sha256}; nothing was kept")


def cached_file(source: str, sha256: str, label: str, offline: bool | None = None) -> Path:
    """The local file of ``source``, downloaded into the cache if needed, its sha256 checked.

    Args:
        source: a local path or a URL.
        sha256: the file's full hex digest.
        label: what the file is, for messages (the weights' name).
        offline: never touch the network (default: ``$AAUTE_OFFLINE``).

    Raises:
        WeightsError: offline and not cached, or a file whose sha256 differs.
        FileNotFoundError: a local file that is gone.
    """
    if is_url(source):
        name = Path(urllib.parse.urlparse(source).path).name or f"{label}.pt"
        path = weights_dir() / "files" / f"{sha256[:12]}-{name}"
        if not path.is_file():
            if offline_mode(offline):
                raise WeightsError(f"weights {label}: offline mode, and {path} is not cached; download "
                                   f"{source} (sha256 {sha256}) and put it at {path}")
            _download(source, path, sha256)
            return path
    else:
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the file of weights {label} is gone (re-run the job that made it "
                                    f"or register the weights again)")
    actual = file_sha256(path)
    if actual != sha256:
        raise WeightsError(f"{path}: sha256 {actual} differs from {sha256} registered for {label} (the file "
                           f"was replaced or damaged; re-register it or delete it to download it again)")
    return path
