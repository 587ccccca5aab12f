"""The MicroPython source a board's natmod is built against (codegen.natmod.sources): downloaded into the cache only
when its SHA-256 matches the pin, said plainly when offline, and used by the build. A loopback HTTP server serves a
tarball made from the shared tree (../shared/micropython, v1.28.0) with its own checksum pinned for the test.
"""

from __future__ import annotations

import hashlib
import http.server
import io
import socket
import tarfile
import threading

import pytest

from codegen.errors import UserError
from codegen.natmod import sources
from conftest import mpy_dir, require_tool

RELEASE = "1.28.0"


@pytest.fixture(scope="module")
def tarball():
    """micropython-1.28.0.tar.xz from the shared tree (what the build needs of it: py/, tools/, lib/libm)."""
    tree = mpy_dir()
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:xz", preset=0) as tar:
        for part in ("py", "tools", "lib/libm", "LICENSE"):
            tar.add(tree / part, arcname=f"micropython-{RELEASE}/{part}")
    return buffer.getvalue()


@pytest.fixture
def server(tarball):
    """A loopback HTTP server with the tarball at /micropython-1.28.0.tar.xz; yields (url template, requests)."""
    requests = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            requests.append(self.path)
            if self.path != f"/micropython-{RELEASE}.tar.xz":
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Length", str(len(tarball)))
            self.end_headers()
            self.wfile.write(tarball)

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}/micropython-{{version}}.tar.xz", requests
    finally:
        httpd.shutdown()
        httpd.server_close()


@pytest.fixture
def isolated(tmp_path, monkeypatch):
    """No MPY_DIR, no shared tree, an empty cache."""
    monkeypatch.delenv("MPY_DIR", raising=False)
    monkeypatch.setenv("DEADRECKON_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr("codegen.tools.SHARED_MICROPYTHON", tmp_path / "no-shared-tree")
    return tmp_path


def test_download_is_checked_cached_and_builds_the_natmod(server, tarball, shared_tree, isolated, monkeypatch):
    require_tool("make")
    require_tool("gcc")
    url, requests = server
    monkeypatch.setenv(sources.URL_ENV, url)
    monkeypatch.setitem(sources.RELEASE_SHA256, RELEASE, hashlib.sha256(tarball).hexdigest())
    said = []
    tree, where = sources.micropython_source(RELEASE, said.append)
    assert tree == isolated / "cache" / "micropython" / RELEASE and "downloaded" in where
    assert sources.tree_release(tree) == RELEASE and (tree / "tools" / "mpy_ld.py").is_file()
    assert any("checked (SHA-256" in line for line in said)
    again, where = sources.micropython_source(RELEASE, said.append)
    assert again == tree and where.startswith("cache") and len(requests) == 1  # no second download

    from codegen.natmod.build import build_module
    from test_kernel_natmod import native_tree

    built = build_module(native_tree(isolated / "gen"), isolated / "work", "x64", RELEASE, progress=said.append)
    assert built.tree == tree and built.module.read_bytes()[:3] == b"M\x06\x0b"  # .mpy 6.3, x64


def test_a_tarball_that_does_not_match_the_pin_is_refused_before_unpacking(server, isolated, monkeypatch):
    url, requests = server
    monkeypatch.setenv(sources.URL_ENV, url)
    monkeypatch.setitem(sources.RELEASE_SHA256, RELEASE, "0" * 64)
    with pytest.raises(UserError, match="not the pinned 0000") as refused:
        sources.micropython_source(RELEASE, lambda _: None)
    assert "nothing unpacked" in refused.value.message and len(requests) == 1
    assert not (isolated / "cache" / "micropython" / RELEASE).exists()
    assert not [p for p in (isolated / "cache" / "micropython").iterdir()]  # no partial download left


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # a port nobody listens on once this socket closes


def test_offline_says_so_and_how_to_build_without_the_network(isolated, monkeypatch):
    monkeypatch.setenv(sources.URL_ENV, f"http://127.0.0.1:{closed_port()}/micropython-{{version}}.tar.xz")
    with pytest.raises(UserError, match=f"cannot download the MicroPython {RELEASE} source") as offline:
        sources.micropython_source(RELEASE, lambda _: None)
    assert "offline?" in offline.value.message and "MPY_DIR" in offline.value.hint


def test_a_release_without_a_pinned_checksum_is_not_downloaded(isolated):
    with pytest.raises(UserError, match="no pinned checksum for the MicroPython 1.99.0 source") as refused:
        sources.micropython_source("1.99.0", lambda _: None)
    assert "MPY_DIR" in refused.value.hint


def test_offline_build_says_the_app_uses_the_fallback(isolated, monkeypatch, tmp_path):
    """`deadreckon build` without network, MPY_DIR or a cached tree still builds the app, and says why there is no
    native module."""
    from codegen.natmod.build import NoRoute, build_module
    from test_kernel_natmod import native_tree

    require_tool("gcc")
    monkeypatch.setenv(sources.URL_ENV, f"http://127.0.0.1:{closed_port()}/micropython-{{version}}.tar.xz")
    with pytest.raises(NoRoute, match="cannot download.*set MPY_DIR"):
        build_module(native_tree(tmp_path / "gen"), tmp_path / "work", "x64", RELEASE, progress=lambda _: None)


@pytest.fixture(scope="module")
def shared_tree():
    return mpy_dir()


def test_mpy_dir_wins_and_must_be_a_tree(shared_tree, isolated, monkeypatch):
    monkeypatch.setenv("MPY_DIR", str(shared_tree))
    tree, where = sources.micropython_source(RELEASE, lambda _: None)
    assert tree == shared_tree and where == f"MPY_DIR ({RELEASE})"
    monkeypatch.setenv("MPY_DIR", str(isolated))
    with pytest.raises(UserError, match="is not a MicroPython source tree"):
        sources.micropython_source(RELEASE, lambda _: None)


def test_the_tree_abi_is_the_one_mpy_ld_and_the_loader_use():
    """The release the boards declare and its native ABI, read from the tree: .mpy 6.3 and an mp_fun_table whose
    type entries start where mpy_ld puts them (its MP_FUN_TABLE_MP_TYPE_TYPE_OFFSET)."""
    import re

    from codegen.tools import mpy_format
    from codegen.natmod.abi import check_header, tree_abi
    from codegen.natmod.mpyfile import Header

    tree = mpy_dir()
    abi = tree_abi(tree)
    assert abi.version == RELEASE and abi.mpy_format == "6.3" == mpy_format(RELEASE)
    offset = int(re.search(r"^MP_FUN_TABLE_MP_TYPE_TYPE_OFFSET = (\d+)", (tree / "tools" / "mpy_ld.py").read_text(),
                           re.M).group(1))
    assert abi.fun_table.index("type_type") == offset == abi.fun_table_index("mp_type_type")
    assert abi.fun_table_index("mp_type_fun_builtin_var") == offset + 8
    assert abi.fun_table[:3] == ("const_none", "const_false", "const_true")
    check_header(Header(6, 3, "xtensawin", 31), "6.3", "xtensawin", RELEASE)
    with pytest.raises(UserError, match=r"\.mpy 6\.2, MicroPython 1\.28\.0 loads native \.mpy 6\.3 only"):
        check_header(Header(6, 2, "xtensawin", 31), "6.3", "xtensawin", RELEASE)
    with pytest.raises(UserError, match="built for armv6m, the board runs xtensawin"):
        check_header(Header(6, 3, "armv6m", 31), "6.3", "xtensawin", RELEASE)


def archive(*members: tuple[str, str, str]) -> tarfile.TarFile:
    """An in-memory tar of (kind, name, content-or-link-target) members, opened for reading."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        for kind, name, payload in members:
            info = tarfile.TarInfo(name)
            if kind == "file":
                info.size = len(payload)
                tar.addfile(info, io.BytesIO(payload.encode()))
            else:
                info.type = {"sym": tarfile.SYMTYPE, "dir": tarfile.DIRTYPE, "fifo": tarfile.FIFOTYPE}[kind]
                info.linkname = payload
                tar.addfile(info)
    buffer.seek(0)
    return tarfile.open(fileobj=buffer)


CHECKS = ["deadreckon's own check (Python < 3.11.4)"] + (["tarfile's data filter"] if hasattr(tarfile, "data_filter")
                                                          else [])


@pytest.mark.parametrize("checked_by", CHECKS)
@pytest.mark.parametrize("hostile", [
    ("file", "../escaped.txt", "x"),
    ("file", "{outside}/absolute.txt", "x"),
    ("sym", "micropython-1.28.0/out", "../../.."),
    ("sym", "micropython-1.28.0/abs", "/etc"),
    ("fifo", "micropython-1.28.0/pipe", ""),
])
def test_an_archive_member_that_leaves_the_tree_is_refused(hostile, checked_by, tmp_path, monkeypatch):
    """Refused (TarError), or, for an absolute name under tarfile's filter, written inside the tree: never outside."""
    if checked_by.startswith("deadreckon"):
        monkeypatch.delattr(tarfile, "data_filter", raising=False)
    kind, name, payload = hostile
    into = tmp_path / "unpacked"
    try:
        sources.unpack(archive(("dir", "micropython-1.28.0", ""), (kind, name.format(outside=tmp_path), payload)), into)
    except tarfile.TarError:
        pass
    else:
        assert kind == "file" and name.startswith("{outside}") and checked_by.startswith("tarfile")
        assert (into / str(tmp_path).lstrip("/") / "absolute.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) in ([], ["unpacked"])


def test_the_fallback_check_unpacks_a_plain_tree_with_in_tree_links(tmp_path, monkeypatch):
    monkeypatch.delattr(tarfile, "data_filter", raising=False)
    into = tmp_path / "unpacked"
    sources.unpack(archive(("dir", "mp", ""), ("file", "mp/py/obj.c", "int x;\n"), ("sym", "mp/link.c", "py/obj.c")),
                   into)
    assert (into / "mp/link.c").read_text() == "int x;\n"
