"""The board commands as a user runs them: validate, generate, boards, schema, config; malformed input corpus."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from codegen.board.loader import bundled_boards
from conftest import ROOT

LOCATED = re.compile(r"^(?P<file>[^:\n]+):(?P<line>\d+):(?P<col>\d+): error: ", re.M)


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run(
        [sys.executable, "-m", "codegen", *args], capture_output=True, text=True, cwd=cwd or ROOT, env=env, timeout=120
    )


def assert_located(result: subprocess.CompletedProcess, line: int, col: int, message: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    match = LOCATED.search(result.stderr)
    assert match, result.stderr
    assert (int(match["line"]), int(match["col"])) == (line, col), result.stderr
    assert message in result.stderr


def write(tmp_path: Path, content: bytes | str, name: str = "board.yaml") -> Path:
    path = tmp_path / name
    if isinstance(content, str):
        content = textwrap.dedent(content).lstrip("\n").encode("utf-8")
    path.write_bytes(content)
    return path


# --- the malformed corpus ------------------------------------------------------------------------------------


def test_tab_indentation(tmp_path):
    path = write(tmp_path, "extends: ttgo-tbeam-v1.1\nimu:\n\taddress: 0x69\n")
    assert_located(run("validate", str(path)), 3, 1, "tab character in indentation")


def test_duplicate_key(tmp_path):
    path = write(tmp_path, """
        extends: ttgo-tbeam-v1.1
        led:
          pin: 13
          pin: 14
    """)
    result = run("validate", str(path))
    assert_located(result, 4, 3, "duplicate key 'pin'")
    assert "the first 'pin' is on line 3" in result.stderr


def test_wrong_types(tmp_path):
    path = write(tmp_path, """
        extends: ttgo-tbeam-v1.1
        imu:
          accel_range_g: 3
          sample_rate_hz: fast
        i2c:
          main:
            frequency: 400000.5
    """)
    result = run("validate", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    located = {(int(m["line"]), int(m["col"])) for m in LOCATED.finditer(result.stderr)}
    assert located == {(3, 18), (4, 19), (7, 16)}, result.stderr
    assert "imu.accel_range_g: should be 2, 4, 8 or 16 (got 3)" in result.stderr
    assert "imu.sample_rate_hz: should be a valid number (got 'fast')" in result.stderr


def test_unknown_key_did_you_mean(tmp_path):
    path = write(tmp_path, """
        extends: ttgo-tbeam-v1.1
        i2c:
          main:
            sdaa: 21
    """)
    result = run("validate", str(path))
    assert_located(result, 4, 5, "unknown key 'sdaa' in i2c.main")
    assert "hint: did you mean `sda`?" in result.stderr
    assert "        sdaa: 21\n        ^\n" in result.stderr  # the offending line and a caret under the key


def test_missing_required_key(tmp_path):
    path = write(tmp_path, """
        name: mine
        imu: {bus: main}
        gps: {uart: gps}
        i2c:
          main: {sda: 21}
        uart:
          gps: {rx: 16}
    """)
    result = run("validate", str(path))
    assert_located(result, 5, 3, "i2c.main is missing required key 'scl'")


def test_empty_file(tmp_path):
    assert_located(run("validate", str(write(tmp_path, b""))), 1, 1, "empty board file")


def test_not_a_mapping(tmp_path):
    assert_located(run("validate", str(write(tmp_path, "- 1\n- 2\n"))), 1, 1, "not a list")


def test_binary_garbage(tmp_path):
    garbage = bytes(range(256)) * 4
    assert_located(run("validate", str(write(tmp_path, b"name: x\n" + garbage))), 2, 1, "binary data")
    assert_located(run("validate", str(write(tmp_path, b"name: x\nled: \xff\xfe\n"))), 2, 6, "not UTF-8")


def test_ten_megabyte_file(tmp_path):
    path = write(tmp_path, b"# padding\n" * 1_000_000)
    assert_located(run("validate", str(path)), 1, 1, "file is 10.0 MB")


def test_yaml_syntax_error(tmp_path):
    path = write(tmp_path, "extends: ttgo-tbeam-v1.1\nimu: {address: 0x69\nled: {pin: 13}\n")
    result = run("validate", str(path))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert LOCATED.search(result.stderr) and "YAML syntax" in result.stderr


def test_missing_file_and_unknown_board(tmp_path):
    result = run("validate", str(tmp_path / "nope.yaml"))
    assert result.returncode == 2 and "no such board file" in result.stderr and "Traceback" not in result.stderr
    result = run("validate", "ttgo-tbeam-v1,1")
    assert result.returncode == 2 and "did you mean `ttgo-tbeam-v1.1`?" in result.stderr


def test_extends_errors(tmp_path):
    result = run("validate", str(write(tmp_path, "extends: ttgo-tbem-v1.1\n")))
    assert_located(result, 1, 10, "`extends: ttgo-tbem-v1.1`: no bundled board by that name")
    write(tmp_path, "extends: b.yaml\nname: a\n", "a.yaml")
    write(tmp_path, "extends: a.yaml\nname: b\n", "b.yaml")
    result = run("validate", str(tmp_path / "a.yaml"))
    assert result.returncode == 2 and "`extends:` forms a cycle" in result.stderr


# --- the commands --------------------------------------------------------------------------------------------


def test_validate_ok_and_strict(tmp_path):
    result = run("validate")
    assert result.returncode == 0 and "ok (ttgo-tbeam-v1.1)" in result.stdout
    path = write(tmp_path, "extends: ttgo-tbeam-v1.1\nled: {pin: 2}\n")
    result = run("validate", str(path))
    assert result.returncode == 0 and ":2:12: warning: led.pin: GPIO2 is a strapping pin" in result.stderr
    result = run("validate", "--strict", str(path))
    assert result.returncode == 2 and ":2:12: error: led.pin: GPIO2 is a strapping pin" in result.stderr


def test_boards_lists_default_first():
    result = run("boards")
    names = [line.split()[0] for line in result.stdout.splitlines()]
    assert names[0] == "ttgo-tbeam-v1.1"
    assert set(names) >= {
        "ttgo-tbeam-v1.0", "ttgo-tbeam-v1.2", "ttgo-tbeam-v0.7", "esp32-devkitc-gy521", "esp32s3-devkitc-gy521",
        "pico-gy521",
    }


def test_schema_validates_the_bundled_boards():
    import jsonschema

    schema = json.loads(run("schema").stdout)
    from codegen.board.yamlsource import read_yaml

    for _, path, _ in bundled_boards():
        jsonschema.validate(read_yaml(path).data, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"name": "x", "imu": {"bus": "main", "adress": 0x68}, "gps": {"uart": "g"}}, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"name": "x"}, schema)


def test_schema_is_json_schema():
    schema = json.loads(run("schema").stdout)
    assert schema["$schema"].endswith("2020-12/schema")
    assert {"imu", "gps", "algorithm", "extends"} <= set(schema["$defs"]["Board"]["properties"])
    assert schema["$defs"]["Algorithm"]["properties"]["block"]["default"] == 16


def test_config_says_where_values_come_from(tmp_path):
    path = write(tmp_path, "extends: ttgo-tbeam-v1.1\nalgorithm:\n  block: 32\n")
    lines = run("config", str(path)).stdout.splitlines()
    by_key = {line.split(":")[0]: line for line in lines}
    assert by_key["algorithm.block"].split("#")[1].strip() == f"{path}:3:10"
    assert "ttgo-tbeam-v1.1.yaml:" in by_key["algorithm.window"]
    assert by_key["micropython.filesystem.block_size"].endswith("# default")
    assert "imu.address: 0x68" in by_key["imu.address"]


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*")) if p.is_file()
    }


@pytest.mark.parametrize("name", [name for name, _, _ in bundled_boards()])
def test_every_bundled_board_generates_byte_identically(tmp_path, name):
    first, second = tmp_path / "a", tmp_path / "b"
    assert run("generate", name, "-o", str(first)).returncode == 0
    assert run("generate", name, "-o", str(second)).returncode == 0
    digest = _tree_digest(first)
    assert digest == _tree_digest(second)
    manifest = json.loads((first / "MANIFEST.json").read_text())
    assert manifest["board"] == name
    listed = {rel: entry["sha256"] for rel, entry in manifest["files"].items()}
    assert listed == {rel: sha for rel, sha in digest.items() if rel != "MANIFEST.json"}
    config = "app/lib/board_config.py" if "app/lib/board_config.py" in listed else "app/board_config.py"  # CircuitPython
    assert config in listed
    assert "imu.address" in manifest["files"][config]["keys"]


def test_generate_protects_foreign_and_edited_folders(tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    result = run("generate", "-o", str(foreign))
    assert result.returncode == 2 and "was not generated by deadreckon" in result.stderr
    assert (foreign / "notes.txt").read_text() == "mine"

    out = tmp_path / "out"
    assert run("generate", "-o", str(out)).returncode == 0
    config = out / "app" / "board_config.py"
    config.write_text(config.read_text() + "# my tweak\n")
    result = run("generate", "-o", str(out))
    assert result.returncode == 2 and "app/board_config.py" in result.stderr and "--force" in result.stderr
    assert config.read_text().endswith("# my tweak\n")
    assert run("generate", "--force", "-o", str(out)).returncode == 0
    assert not config.read_text().endswith("# my tweak\n")


def test_retarget_by_yaml_alone(tmp_path):
    """A user puts the IMU on a second bus on two header pins with a few lines; the constants follow (the T-Beam's
    AXP192 stays on its soldered I2C0 at 21/22)."""
    path = write(tmp_path, """
        extends: ttgo-tbeam-v1.1
        i2c:
          imu: {id: 1, sda: 13, scl: 14}
        imu: {bus: imu, address: 0x69, axes: [-y, x, z]}
    """)
    assert run("generate", str(path), "-o", str(tmp_path / "out")).returncode == 0
    config = (tmp_path / "out" / "app" / "board_config.py").read_text()
    assert "IMU_I2C_ID = const(1)" in config
    assert "IMU_SDA = const(13)" in config and "IMU_SCL = const(14)" in config
    assert "PMU_I2C_ID = const(0)" in config
    assert "IMU_ADDR = const(0x69)" in config
    assert "IMU_AXIS_MAP = ((1, -1), (0, 1), (2, 1), )" in config


def test_moving_the_bus_of_a_soldered_part_is_an_error_at_the_pin(tmp_path):
    """The T-Beam's AXP192 is soldered to 21/22: moving its bus leaves the GPS unpowered on the board."""
    path = write(tmp_path, """
        extends: ttgo-tbeam-v1.1
        i2c:
          main: {sda: 13, scl: 14}
    """)
    assert_located(run("validate", str(path)), 3, 15,
                   "i2c.main.sda: GPIO13, but this board's AXP192 power chip (power.bus: main) is soldered to "
                   "SDA GPIO21 / SCL GPIO22")


def test_generate_removes_stale_files_it_wrote_and_keeps_edited_ones(tmp_path):
    """A file an older generation wrote and this one does not: removed while unedited, kept (and named) once the
    user edited it, even with --force."""
    from codegen.generate import seal

    out = tmp_path / "out"
    assert run("generate", "-o", str(out)).returncode == 0

    def add_stale(text: str, recorded: str) -> None:
        manifest = json.loads((out / "MANIFEST.json").read_text())
        manifest.pop("seal")
        manifest["files"]["app/old_module.py"] = {"sha256": hashlib.sha256(recorded.encode()).hexdigest()}
        (out / "MANIFEST.json").write_text(json.dumps(seal(manifest)))
        (out / "app" / "old_module.py").write_text(text)

    add_stale("X = 1\n", "X = 1\n")
    assert run("generate", "-o", str(out)).returncode == 0
    assert not (out / "app" / "old_module.py").exists()

    add_stale("X = 2  # my change\n", "X = 1\n")
    result = run("generate", "-o", str(out))
    assert result.returncode == 2 and "app/old_module.py" in result.stderr
    result = run("generate", "--force", "-o", str(out))
    assert result.returncode == 0 and "kept 1 edited file(s)" in result.stderr and "app/old_module.py" in result.stderr
    assert (out / "app" / "old_module.py").read_text() == "X = 2  # my change\n"
    assert "app/old_module.py" not in json.loads((out / "MANIFEST.json").read_text())["files"]
