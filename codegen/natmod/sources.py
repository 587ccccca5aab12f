"""The MicroPython source tree a board's native module is built against: the release the board declares.

In order: MPY_DIR (the user's tree, any release: its ABI is checked against the board's after the build); the
shared v1.28.0 tree beside a source checkout (../shared/micropython) when the board declares that release; the
cache ($DEADRECKON_CACHE/micropython/RELEASE); else the release's source tarball is downloaded into the cache,
pinned by its SHA-256 (a release without a pinned checksum is not downloaded), checked before anything is unpacked.
DEADRECKON_MICROPYTHON_URL replaces the download address (a template with {version}, e.g. a local mirror); the
checksum stays pinned.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tarfile
import tempfile
import urllib.error
import urllib.request
from pathlib import Path
from typing import Callable, Optional

from codegen import tools
from codegen.errors import UserError

# SHA-256 of micropython-RELEASE.tar.xz, the source archive published with each release (it carries the lib/
# submodules the auto-generated archives lack); from the release assets, as package managers pin them.
RELEASE_SHA256 = {
    "1.24.1": "5d624a0b23389134d963b204601db9bc4ca57bfb615d13f13592bc2b5b494c03",
    "1.25.0": "9fe99ad5808e66bb40d374f5cad187c32c7d1c49cf47f72b38fd453c28c2aebe",
    "1.26.1": "12be6514df6272c0fcb328122b534af6b12abdd52435c19f40ee1707cc43ac98",
    "1.27.0": "9874b20646c3bbe81d524f779a16875e5d088b7065e175ffd2aa2a02f50573c9",
    "1.28.0": "4e43c59657b8da33b4bc503509a827cc3ea6cb66c446475c57776cf4467ba215",
}
RELEASE_URL = "https://github.com/micropython/micropython/releases/download/v{version}/micropython-{version}.tar.xz"
URL_ENV = "DEADRECKON_MICROPYTHON_URL"
DOWNLOAD_TIMEOUT_S = 60
MARKER = ".deadreckon-source"  # written last into a cached tree: its release and checksum

Progress = Callable[[str], None]


def cache_root() -> Path:
    root = os.environ.get("DEADRECKON_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "deadreckon") / "micropython"


def is_tree(path: Path) -> bool:
    return (Path(path) / "py" / "dynruntime.mk").is_file()


def tree_release(path: Path) -> Optional[str]:
    """The release ("1.28.0") of the MicroPython tree at `path`, from py/mpconfig.h; None if unreadable."""
    from codegen.natmod.abi import tree_abi

    try:
        return tree_abi(Path(path)).version
    except (OSError, UserError):
        return None


def micropython_source(version: str, progress: Progress = print) -> tuple[Path, str]:
    """(tree, where it came from) for building natmods for MicroPython `version`; UserError when none can be had."""
    chosen = os.environ.get("MPY_DIR")
    if chosen:
        if not is_tree(Path(chosen)):
            raise UserError(f"MPY_DIR={chosen} is not a MicroPython source tree (no py/dynruntime.mk)",
                            hint="point MPY_DIR at the top of a MicroPython checkout, or unset it")
        return Path(chosen), f"MPY_DIR ({tree_release(Path(chosen)) or 'unknown release'})"
    shared = tools.SHARED_MICROPYTHON
    if is_tree(shared) and tree_release(shared) == version:
        return shared, f"{shared} ({version})"
    cached = cache_root() / version
    if (cached / MARKER).is_file() and is_tree(cached):
        return cached, f"cache {cached}"
    return fetch_release(version, progress), f"downloaded into {cached}"


def fetch_release(version: str, progress: Progress = print) -> Path:
    """Download, check and unpack the source of MicroPython `version` into the cache; return the tree."""
    pinned = RELEASE_SHA256.get(version)
    if pinned is None:
        raise UserError(
            f"deadreckon has no pinned checksum for the MicroPython {version} source, so it does not download it",
            hint=f"set MPY_DIR to a MicroPython {version} source tree, or declare a release deadreckon pins "
                 f"(micropython.version: {', '.join(RELEASE_SHA256)})")
    url = os.environ.get(URL_ENV, RELEASE_URL).format(version=version)
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    target = root / version
    progress(f"  fetching the MicroPython {version} source (natmod headers and linker) from {url}")
    with tempfile.TemporaryDirectory(dir=root, prefix=f".{version}-") as tmp:
        archive = Path(tmp) / "source.tar.xz"
        try:
            with urllib.request.urlopen(url, timeout=DOWNLOAD_TIMEOUT_S) as answer, open(archive, "wb") as out:
                shutil.copyfileobj(answer, out)
        except (urllib.error.URLError, OSError, ValueError) as exc:
            reason = getattr(exc, "reason", None) or exc
            raise UserError(
                f"cannot download the MicroPython {version} source from {url} ({reason}): offline?",
                hint=f"connect once (the source is kept in {root}), or set MPY_DIR to a MicroPython {version} "
                     "source tree; without either the app uses the pure-Python fallback") from None
        digest = hashlib.sha256(archive.read_bytes()).hexdigest()
        if digest != pinned:
            raise UserError(f"the MicroPython {version} source from {url} has SHA-256 {digest}, not the pinned "
                            f"{pinned}: refused (nothing unpacked)",
                            hint=f"check {URL_ENV} if set; a changed release archive needs a deadreckon update")
        unpacked = Path(tmp) / "unpacked"
        try:
            with tarfile.open(archive) as tar:
                tar.extractall(unpacked, filter="data")
        except (tarfile.TarError, OSError) as exc:
            raise UserError(f"the MicroPython {version} source archive does not unpack: {exc}") from None
        tops = [p for p in unpacked.iterdir() if p.is_dir()]
        if len(tops) != 1 or not is_tree(tops[0]) or tree_release(tops[0]) != version:
            raise UserError(f"the archive from {url} is not the MicroPython {version} source tree")
        (tops[0] / MARKER).write_text(f"{version} {digest}\n")
        if target.exists():
            shutil.rmtree(target)
        tops[0].rename(target)
    progress(f"  MicroPython {version} source checked (SHA-256 {pinned[:12]}...) and kept in {target}")
    return target
