"""The build record: what `deadreckon build` compiled, so `flash` and `upload` never send a stale build.

    OUT/build/BUILD.json   the SHA-256 of every file under OUT/app/ the build compiled, and the board content
                           hash from OUT/MANIFEST.json, sealed as the manifest is

`flash` and `upload` compare OUT/app/ with the record before they touch a port, and refuse, naming the files, when
the tree was regenerated (or edited) after the build: the board would otherwise get the old pins. Content hashes,
not modification times: a copied or checked-out tree keeps its hashes, not its times.

`build` itself replaces OUT/build/ only when it is what a build makes: a real folder (not a link) holding app/,
native/, fs.img and the record, so a folder of the user's that happens to be called build/ is never deleted.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path
from typing import Optional

from codegen import __version__
from codegen.errors import UserError
from codegen.safeio import write_atomically

RECORD = "BUILD.json"
UPLOAD_RECORD = "UPLOADED.json"  # what `upload --drive` last sent from this tree (codegen/deploy/drive.py)
BUILD_ENTRIES = {"app", "native", "fs.img", RECORD, UPLOAD_RECORD}  # everything OUT/build/ holds
MAX_RECORD_BYTES = 1024 * 1024


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def source_hashes(out: Path) -> dict[str, str]:
    """SHA-256 of each regular file under OUT/app/ (as `app/...` paths), what a build compiles."""
    app = Path(out) / "app"
    found = {}
    for path in sorted(app.rglob("*")):
        if "__pycache__" in path.parts or not stat.S_ISREG(path.lstat().st_mode):
            continue
        found[path.relative_to(out).as_posix()] = _sha256(path)
    return found


def _board_sha256(out: Path) -> Optional[str]:
    try:
        manifest = json.loads((Path(out) / "MANIFEST.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return manifest.get("board_sha256") if isinstance(manifest, dict) else None


def prepare_build_folder(build_dir: Path) -> None:
    """Refuse to build into OUT/build/ unless it is missing or holds only what a build makes, with no links; then
    forget the last build's record, so a build that fails half way leaves nothing `flash` or `upload` would send."""
    if not os.path.lexists(build_dir):
        return
    if build_dir.is_symlink() or not build_dir.is_dir():
        raise UserError(f"{build_dir} is {'a symbolic link' if build_dir.is_symlink() else 'not a folder'}; "
                        "`deadreckon build` writes only into a real folder it made",
                        hint=f"move {build_dir} away and build again")
    links = sorted(entry.name for entry in build_dir.iterdir() if entry.is_symlink())
    if links:
        raise UserError(f"{build_dir / links[0]} is a symbolic link, which `deadreckon build` did not make; "
                        "refusing to replace it (that would write through it)",
                        hint=f"remove the link from {build_dir} and build again")
    foreign = sorted(entry.name for entry in build_dir.iterdir() if entry.name not in BUILD_ENTRIES)
    if foreign:
        raise UserError(
            f"{build_dir} holds {', '.join(foreign[:3])}, which `deadreckon build` did not make; "
            "refusing to replace the folder",
            hint=f"move your files out of {build_dir} (build replaces it whole) and build again",
        )
    if os.path.lexists(build_dir / RECORD):
        (build_dir / RECORD).unlink()


def record_build(out: Path, sources: dict[str, str]) -> Path:
    """Write OUT/build/BUILD.json for a build of `sources` (from `source_hashes` before compiling)."""
    from codegen.generate import seal

    record = seal({"generator": f"deadreckon {__version__} build", "sources": sources,
                   "board_sha256": _board_sha256(out)})
    path = Path(out) / "build" / RECORD
    write_atomically(path, (json.dumps(record, indent=2, sort_keys=True) + "\n").encode("utf-8"))
    return path


def _read_record(out: Path) -> Optional[dict]:
    from codegen.generate import is_sealed
    from codegen.safeio import read_bounded

    path = Path(out) / "build" / RECORD
    if not os.path.lexists(path) or path.is_symlink():
        return None
    try:
        record = json.loads(read_bounded(path, str(path), MAX_RECORD_BYTES, what="build record").decode("utf-8"))
    except (UserError, ValueError, RecursionError):
        return None
    return record if is_sealed(record) and isinstance(record.get("sources"), dict) else None


def check_build_current(out: Path) -> None:
    """Raise a UserError naming the files when OUT/app/ changed after the build in OUT/build/ was made."""
    out = Path(out)
    rebuild = f"run `deadreckon build {out}` first"
    record = _read_record(out)
    if record is None:
        raise UserError(f"{out / 'build'} has no valid build record ({RECORD}): it is not a build of this tree by "
                        "this deadreckon", hint=rebuild)
    built = record["sources"]
    now = source_hashes(out)
    changed = [rel for rel in now if rel in built and now[rel] != built[rel]]
    added = [rel for rel in now if rel not in built]
    removed = [rel for rel in built if rel not in now]
    if record.get("board_sha256") != _board_sha256(out):
        changed.insert(0, "MANIFEST.json (regenerated from a changed board)")
    if changed or added or removed:
        parts = []
        if changed:
            parts.append(f"changed after it: {', '.join(changed[:5])}")
        if added:
            parts.append(f"new since: {', '.join(added[:5])}")
        if removed:
            parts.append(f"removed since: {', '.join(removed[:5])}")
        raise UserError(f"the build in {out / 'build'} is older than its generated sources ({'; '.join(parts)})",
                        hint=f"{rebuild}: the board would get the old app")
