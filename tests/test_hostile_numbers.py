"""Numbers and `extends:` a careless or hostile board file gives: every number finite and bounded where the app uses
it (YAML's .inf and .nan, a subnormal 1e-320, an integer of 23 digits), and `extends:` that cannot leave
board_configs/ by a bundled name, hold a NUL, loop through links or overflow a file name.

Each case runs `deadreckon generate` through the CLI: exit 2, an `error:` at FILE:LINE:COL with a hint, no
traceback, within the bound, nothing written (the output folder is not even created).
"""

from __future__ import annotations

import pytest

from codegen.board.schema import board_json_schema
from hostilekit import assert_refused, run_cli, snapshot, user_files

BASE = "extends: ttgo-tbeam-v1.1\n"
LONG = "a" * 300


def _loop(home):
    (home / "loop1.yaml").symlink_to("loop2.yaml")
    (home / "loop2.yaml").symlink_to("loop1.yaml")


# (id, board text, extra setup, the board argument, phrases the message must hold)
CASES = [
    ("fix-timeout-inf", BASE + "gps: {fix_timeout_s: .inf}\n", None, "b.yaml",
     ["b.yaml:2:22: error: gps.fix_timeout_s: should be a finite number", "hint: "]),
    ("imu-log-rate-subnormal", BASE + "logging: {imu_rate_hz: 1.0e-320}\n", None, "b.yaml",
     ["b.yaml:2:24: error: logging.imu_rate_hz: should be greater than or equal to 0.01", "hint: "]),
    ("motion-threshold-inf", BASE + "algorithm: {motion_threshold_g: .inf}\n", None, "b.yaml",
     ["b.yaml:2:33: error: algorithm.motion_threshold_g: should be a finite number"]),
    ("fused-align-min-inf", BASE + "algorithm: {fused_kf_align_min: .inf}\n", None, "b.yaml",
     ["b.yaml:2:33: error: algorithm.fused_kf_align_min: should be a finite number"]),
    ("fused-tau-nan", BASE + "algorithm: {fused_tilt_tau_s: .nan}\n", None, "b.yaml",
     ["algorithm.fused_tilt_tau_s: should be a finite number"]),
    ("fused-tau-huge", BASE + "algorithm: {fused_tilt_tau_s: 1.0e300}\n", None, "b.yaml",
     ["algorithm.fused_tilt_tau_s: should be less than or equal to 1000000", "deadreckon schema"]),
    ("reciprocal-of-a-subnormal", BASE + "algorithm: {fused_tilt_tau_dark_s: 1.0e-300}\n", None, "b.yaml",
     ["algorithm.fused_tilt_tau_dark_s: too small to mean anything here", "hint: write 0 where 0 is allowed"]),
    ("sample-rate-subnormal", BASE + "imu: {sample_rate_hz: 1.0e-300}\n", None, "b.yaml",
     ["imu.sample_rate_hz: too small"]),
    ("reserved-pin-23-digits", BASE + "reserved: {x: [99999999999999999999999]}\n", None, "b.yaml",
     ["b.yaml:2:16: error: reserved.x[0]: should be less than or equal to 63"]),
    ("block-23-digits", BASE + "algorithm: {block: 99999999999999999999999}\n", None, "b.yaml",
     ["algorithm.block: should be less than or equal to 4096"]),
    ("extends-nul", 'extends: "ttgo\\0tbeam"\nname: x\n', None, "b.yaml",
     ["b.yaml:1:10: error: `extends:` contains a NUL character", "hint: "]),
    ("extends-link-loop", "extends: ./loop1.yaml\nname: x\n", _loop, "b.yaml",
     ["b.yaml:1:10: error: loop1.yaml: Too many levels of symbolic links", "hint: a link that points back"]),
    ("main-file-link-loop", "name: x\n", _loop, "loop1.yaml",
     ["error: loop1.yaml: Too many levels of symbolic links", "hint: "]),
    ("extends-out-of-board-configs", "extends: ../../../../../../../../../../../home/evil\nname: x\n",
     lambda home: (home / "evil.yaml").write_text((home / "b.yaml").read_text()), "b.yaml",
     ["b.yaml:1:10: error: `extends: ../../", "is neither a bundled board's name", "hint: "]),
    ("extends-300-character-name", f"extends: {LONG}\nname: x\n", None, "b.yaml",
     ["b.yaml:1:10: error: `extends: aaaa", "at most 64 characters"]),
    ("extends-300-character-file", f"extends: ./{LONG}.yaml\nname: x\n", None, "b.yaml",
     ["b.yaml:1:10: error: ", "File name too long", "hint: the file system takes names of at most 255 bytes"]),
]


@pytest.mark.parametrize("text,setup,board,phrases", [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_hostile_number_or_extends_is_refused(tmp_path, text, setup, board, phrases):
    home = tmp_path / "home"
    home.mkdir()
    user_files(home)
    (home / "b.yaml").write_text(text)
    if setup is not None:
        setup(home)
    before = snapshot(home)
    outcome = run_cli("generate", board, "-o", "out", cwd=home)
    assert_refused(outcome, *phrases)
    assert snapshot(home) == before


def _numbers(node, path=""):
    """(path, schema) of every number or integer in the JSON schema (through anyOf, items, additionalProperties)."""
    if isinstance(node, dict):
        if node.get("type") in ("number", "integer"):
            yield path, node
        for key, child in node.items():
            yield from _numbers(child, f"{path}/{key}")
    elif isinstance(node, list):
        for index, child in enumerate(node):
            yield from _numbers(child, f"{path}/{index}")


def test_the_schema_bounds_every_number():
    """Every number a board file takes has an upper bound in the schema `deadreckon schema` prints (a choice of
    values is bounded by its list); the partial (extending) variants share them."""
    found = list(_numbers(board_json_schema()))
    assert len(found) > 60
    unbounded = [path for path, node in found if "maximum" not in node and "exclusiveMaximum" not in node
                 and "enum" not in node and "const" not in node]
    assert unbounded == []
