"""The output folder of `deadreckon post`: it only ever replaces files it wrote itself, never an input, never a file
of the user's, and never through a link; every file lands whole (written aside, then renamed).

What post wrote is listed with its SHA-256 in `post-manifest.json`; a file of an output's name that the manifest does
not list, or that changed since, is the user's. The check runs before any processing, so a refusal costs nothing.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Iterable

from codegen.errors import UserError
from codegen.safeio import write_failed

MANIFEST = "post-manifest.json"
WRITER = "deadreckon post"
OUTPUT_NAMES = ("trajectory.csv", "trajectory.gpx", "trajectory.html", "angles.csv", "report.txt", "report.json",
                "angles.png", "velocity.png", "trajectory.png", "delay.png")


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _manifest(folder: Path) -> dict[str, str]:
    """{name: sha256} of what post wrote here before; {} when there is no manifest or it is not post's."""
    path = folder / MANIFEST
    if not path.is_file() or path.is_symlink():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(data, dict) or data.get("written_by") != WRITER or not isinstance(data.get("files"), dict):
        return {}
    return {str(k): str(v) for k, v in data["files"].items() if k in OUTPUT_NAMES}


def _is_ours(path: Path, manifest: dict[str, str]) -> bool:
    return path.name in manifest and path.is_file() and not path.is_symlink() and _sha256(path) == manifest[path.name]


def check_output_folder(folder: Path, inputs: Iterable[Path]) -> None:
    """Refuse, before anything runs, an output folder where writing would replace an input or a file post did not
    write (or one changed since it did)."""
    folder = Path(folder)
    if folder.is_symlink() and not folder.exists():
        raise UserError(f"output folder {folder} is a broken link", hint="give -o a folder name (it is created)")
    if folder.exists() and not folder.is_dir():
        raise UserError(f"output folder {folder} is an existing file, not a folder",
                        hint="give -o a folder name (it is created); the file is left as it is")
    if not folder.exists():
        parent = folder.resolve().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK):
            raise UserError(f"cannot create output folder {folder}: {parent} is not writable")
        return
    if not os.access(folder, os.W_OK):
        raise UserError(f"output folder {folder} is not writable", hint="choose another folder with -o")
    resolved_inputs = {Path(p).resolve() for p in inputs}
    expanded = set(resolved_inputs)
    for p in resolved_inputs:
        if p.is_dir():
            expanded.update(q.resolve() for q in p.iterdir())
    manifest = _manifest(folder)
    theirs = []
    for name in OUTPUT_NAMES + (MANIFEST,):
        path = folder / name
        if not path.exists() and not path.is_symlink():
            continue
        if path.resolve() in expanded:
            raise UserError(f"{path} is an input of this run; writing {name} there would replace it",
                            hint="choose another output folder with -o")
        if name == MANIFEST:
            if not manifest and path.exists():
                theirs.append(name)
            continue
        if path.is_symlink() or path.is_dir() or not _is_ours(path, manifest):
            theirs.append(name)
    if theirs:
        raise UserError(f"output folder {folder} holds {', '.join(theirs)}, which deadreckon post did not write "
                        "(or which changed since it did); it replaces nothing of yours",
                        hint="choose another (or a new) folder with -o, or move those files away")


def write_files(folder: Path, contents: dict[str, bytes]) -> dict[str, Path]:
    """Write {name: bytes} into folder (created), each via a temporary file renamed into place; then the manifest;
    then remove this folder's earlier outputs that this run did not write again (only if unchanged since)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    old = _manifest(folder)
    written: dict[str, Path] = {}
    hashes: dict[str, str] = {}
    for name, data in contents.items():
        if name not in OUTPUT_NAMES:
            raise ValueError(f"{name} is not an output of post")
        written[name] = _replace(folder / name, data)
        hashes[name] = hashlib.sha256(data).hexdigest()
    _replace(folder / MANIFEST, (json.dumps({"written_by": WRITER, "files": hashes}, indent=2) + "\n").encode())
    for name in set(old) - set(contents):
        path = folder / name
        if _is_ours(path, old):
            path.unlink()
    return written


def _replace(path: Path, data: bytes) -> Path:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as error:
        raise write_failed(path, error) from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
