"""The kernels' declaration (codegen/kernel/layout.py) and what is rendered from it.

- The offsets the app reads keep their values (a field added in the wrong place would move them).
- The C header's macros and structs, the fallback's const()s and the reference's vector are the declaration's.
- Every limit of every fused parameter is enforced alike by the board validation, the C dr_fused_config_set and the
  fallback's fused_init: a value just outside is refused by all three, the value on the limit accepted by all three.
- Adding a state field and a parameter to the declaration, and nothing else, gives C that compiles and a fallback
  that runs and checks the new parameter: the "one edit" the declaration promises.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import os
import re
import subprocess

import pytest

from codegen.board.loader import load_board
from codegen.errors import UserError
from codegen.generate import render_tree
from codegen.kernel import fused as F
from codegen.kernel import layout as L
from conftest import require_tool

TREE = render_tree(load_board())
HEADER = TREE["native/dr_layout.h"].content.decode()
FALLBACK = TREE["app/dr_fallback.py"].content.decode()


def _fallback_consts(source: str) -> dict[str, int]:
    consts = {}
    for node in ast.parse(source).body:
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)
                and getattr(node.value.func, "id", "") == "const" and isinstance(node.targets[0], ast.Name)):
            try:
                consts[node.targets[0].id] = int(eval(compile(ast.Expression(node.value.args[0]), "", "eval"),
                                                      {}, dict(consts)))
            except NameError:
                pass
    return consts


def _macros(header: str) -> dict[str, int]:
    return {m[1]: int(m[2]) for m in re.finditer(r"^#define (\w+) \((-?\d+)\)", header, re.M)}


def test_the_offsets_the_app_reads_keep_their_values():
    consts = _fallback_consts(FALLBACK)
    assert (consts["Q"], consts["V"], consts["GYRO_BIAS"], consts["FIX_AE"], consts["COV_REPAIRS"]) == (0, 4, 7, 50, 142)
    assert (consts["FUSED_GYRO_BIAS"], consts["CAL_MOVED"]) == (4, 149)
    assert consts["FUSED_STATE_LEN"] == 222 and consts["OUT_LEN"] == 6
    # documented in native_ext/API.md: speed 16, East/North 30/31, flags 32
    assert [F.IDX[n] for n in ("speed", "pe", "pn", "flags")] == [16, 30, 31, 32]
    assert L.LAYOUT.seed_header_floats == 22


def test_c_header_fallback_and_reference_follow_the_declaration():
    macros = _macros(HEADER)
    consts = _fallback_consts(FALLBACK)
    for kernel in L.LAYOUT.kernels:
        assert macros[f"{kernel.macro}_STATE_FLOATS"] == kernel.state_floats
        assert macros[f"{kernel.macro}_CONFIG_FLOATS"] == kernel.config_floats
        assert macros[f"{kernel.macro}_PARAMS"] == len(kernel.params)
        for f in kernel.state:
            assert macros[f"{kernel.macro}_STATE_{f.name.upper()}"] == kernel.state_offsets[f.name]
    fused = L.FUSED
    for f in fused.state:
        assert consts[f"_F_{f.name.upper()}"] == fused.state_offsets[f.name], f.name
    for name, at in L.LAYOUT.fused_config_in_buffer().items():
        assert consts[f"_FC_{name.upper()}"] == at, name
    for f in L.SEED.config:
        assert consts[f"_K_{f.name.upper()}"] == L.SEED.config_offsets[f.name], f.name
    for flag in fused.flags:
        assert macros[f"DR_FUSED_{flag.name}"] == consts[f"_{flag.name}"] == flag.value == getattr(F, flag.name)
    for i, p in enumerate(fused.params):
        assert macros[f"DR_FUSED_P_{p.name.upper()}"] == i
    assert [f.name for f in dataclasses.fields(F.FusedConfig)] == list(fused.param_names)
    assert F.STATE_FIELDS == fused.element_names() and F.STATE_LEN == fused.state_floats
    assert F.FusedConfig() == F.FusedConfig.from_board(load_board().board)  # the board's defaults are the declared


def test_the_compiled_structs_have_the_declared_sizes():
    require_tool("cc")
    from codegen.kernel.hostfused import load_fused
    from codegen.kernel.hostkernel import load_kernel

    fk, kernel = load_fused(), load_kernel()
    for ffi, struct, floats in ((fk.ffi, "dr_fused_state", L.FUSED.state_floats),
                                (fk.ffi, "dr_fused_config", L.FUSED.config_floats),
                                (kernel.ffi, "dr_state", L.SEED.state_floats),
                                (kernel.ffi, "dr_config", L.SEED.config_floats)):
        assert ffi.sizeof(struct) == 4 * floats, struct


def _limit_cases():
    """(parameter, value, accepted, the other parameters' values) at and just beyond each declared limit of each fused
    parameter. A parameter another is declared at most gets that one at 0, so only its own limit decides."""
    cases = []
    for p in L.FUSED.params:
        others = {q.name: 0.0 for q in L.FUSED.params if q.at_most == p.name}
        if p.kind == "choice":
            last = len(p.choices) - 1
            cases += [(p.name, -1, False, {}), (p.name, 0, True, {}), (p.name, last, True, {}),
                      (p.name, last + 1, False, {})]
        if p.gt is not None:
            cases += [(p.name, p.gt, False, others), (p.name, p.gt + 1e-3, True, others)]
        if p.ge is not None:
            cases += [(p.name, p.ge - 1e-3, False, others), (p.name, p.ge, True, others)]
        if p.le is not None:
            cases += [(p.name, p.le + 1e-3, False, others), (p.name, p.le, True, others)]
        if p.at_most is not None:
            limit = L.FUSED.param(p.at_most).default
            cases += [(p.name, limit + 1.0, False, {}), (p.name, limit, True, {})]
    return cases


LIMIT_CASES = _limit_cases()


def _params(name, value, others) -> dict:
    return {**others, name: float(value)}


def test_every_limit_is_declared_somewhere():
    checked = {name for name, _, _, _ in LIMIT_CASES}
    unchecked = {p.name for p in L.FUSED.params if p.kind != "bool"} - checked
    assert not unchecked, f"parameters without a limit: {unchecked}"


@pytest.mark.parametrize("name,value,accepted,others", LIMIT_CASES,
                         ids=[f"{n}={v:g}" for n, v, _, _ in LIMIT_CASES])
def test_board_and_c_enforce_each_limit(tmp_path, name, value, accepted, others):
    require_tool("cc")
    from codegen.kernel.hostfused import load_fused

    board = tmp_path / "board.yaml"
    choices = L.FUSED.param(name).choices  # a choice's board key takes its name, the kernels its index
    board_value = {name: choices[int(value)] if choices and accepted else value}
    keys = "".join(f"  fused_{key}: {x!r}\n" for key, x in {**others, **board_value}.items())
    board.write_text(f"extends: ttgo-tbeam-v1.1\nname: limits\nalgorithm:\n{keys}")
    if accepted:
        load_board(board)
    else:
        with pytest.raises(UserError) as problem:
            load_board(board)
        assert f"fused_{name}" in problem.value.render()
    params = dataclasses.replace(F.FusedConfig(), **_params(name, value, others))
    if accepted:
        load_fused().session(params)
    else:
        with pytest.raises(ValueError):
            load_fused().session(params)


CHECK_SCRIPT = """
import json, sys
from array import array
import dr_fallback as dr
st = array('f', [0.0] * dr.FUSED_STATE_LEN)
for params in json.loads(open(sys.argv[1]).read()):
    try:
        dr.fused_init(st, params)
        print('ok')
    except ValueError as e:
        print('ValueError', e)
"""


def test_fallback_enforces_each_limit(tmp_path):
    micropython = require_tool("micropython")
    from kernelkit import write_fallback

    write_fallback(tmp_path)
    defaults = [float(getattr(F.FusedConfig(), n)) for n in L.FUSED.param_names]
    arrays = []
    for name, value, _, others in LIMIT_CASES:
        params = list(defaults)
        for key, x in _params(name, value, others).items():
            params[L.FUSED.param_names.index(key)] = x
        arrays.append(params)
    (tmp_path / "cases.json").write_text(json.dumps(arrays))
    (tmp_path / "check.py").write_text(CHECK_SCRIPT)
    done = subprocess.run([micropython, str(tmp_path / "check.py"), str(tmp_path / "cases.json")], capture_output=True,
                          text=True, env=dict(os.environ, MICROPYPATH=str(tmp_path)), timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == len(LIMIT_CASES)
    for (name, value, accepted, _), line in zip(LIMIT_CASES, lines):
        if accepted:
            assert line == "ok", (name, value, line)
        else:
            assert line.startswith(f"ValueError {name} must be "), (name, value, line)


def test_adding_a_field_and_a_parameter_is_one_edit(tmp_path, monkeypatch):
    """A declaration with one more state field (before the median ring), one more parameter and one more choice (a
    receiver model), nothing else changed: the board gets the keys (defaults, limits, the choices), the
    rendered C compiles under the strict flags with the field, the parameters' board values, checks, conversions and
    the choices' names, and the fallback grows by all three, runs the fused steps and refuses each new parameter
    outside its limits; the public offsets stay."""
    cc = require_tool("cc")
    micropython = require_tool("micropython")
    from pydantic import ValidationError

    import codegen.generate
    from codegen.board import model

    fused = L.FUSED
    ring = [f.name for f in fused.state].index("med_i")
    extra_field = L.Field("lateral", "m/s", "velocity across the travel direction")
    extra_param = L.Param("lateral_tau_s", "s", "time constant of the lateral velocity decay (0: none)",
                          L.Store("inv_lateral_tau", "1/s", "rate"), 2.0, ge=0)
    receiver = L.Param("receiver", "", "the GPS receiver's model", L.Store("receiver", "choice"), "neo6m",
                       kind="choice", choices=("neo6m", "neo8m", "other"))
    grown = dataclasses.replace(fused, state=fused.state[:ring] + (extra_field,) + fused.state[ring:],
                                params=fused.params + (extra_param, receiver))
    L.check(grown)
    algorithm = model.algorithm_model(grown)
    with pytest.raises(ValidationError, match="fused_lateral_tau_s"):
        algorithm(fused_lateral_tau_s=-1.0)
    with pytest.raises(ValidationError, match="fused_receiver"):
        algorithm(fused_receiver="sirf")
    assert algorithm(fused_receiver="neo8m").fused_receiver == "neo8m"
    loaded = load_board()
    board = loaded.board.model_copy(update={"algorithm": algorithm(**loaded.board.algorithm.model_dump())})
    monkeypatch.setattr(codegen.generate, "LAYOUT", dataclasses.replace(L.LAYOUT, fused=grown))
    tree = render_tree(dataclasses.replace(loaded, board=board))
    assert "#define DR_FUSED_LATERAL_TAU_S (2.0f) /* s */" in tree["native/dr_board.h"].content.decode()
    assert "#define DR_FUSED_RECEIVER (0.0f)" in tree["native/dr_board.h"].content.decode()
    native = tmp_path / "native"
    native.mkdir()
    for path, f in tree.items():
        if path.startswith("native/"):
            (native / path[7:]).write_bytes(f.content)
    for source in ("dr_kernel.c", "dr_fused.c", "dr_median.c", "dr_geo.c"):
        done = subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-c", source, "-o",
                               source + ".o"], cwd=native, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    header = (native / "dr_layout.h").read_text()
    macros = _macros(header)
    floats, params, lateral = fused.state_floats + 1, len(fused.params) + 2, fused.state_offsets["med_i"]
    assert macros["DR_FUSED_STATE_FLOATS"] == floats and macros["DR_FUSED_PARAMS"] == params
    assert (macros["DR_FUSED_RECEIVER_NEO6M"], macros["DR_FUSED_RECEIVER_NEO8M"]) == (0, 1)
    assert "!(p[DR_FUSED_P_RECEIVER] >= 0.0f) || !(p[DR_FUSED_P_RECEIVER] <= 2.0f)" in header
    assert macros["DR_FUSED_STATE_LATERAL"] == lateral and macros["DR_FUSED_STATE_FIX_AE"] == 50
    assert "float lateral; /* m/s: velocity across the travel direction */" in header
    assert "cfg->inv_lateral_tau = p[DR_FUSED_P_LATERAL_TAU_S] > 0.0f ?" in header
    app = tmp_path / "app"
    app.mkdir()
    (app / "dr_fallback.py").write_bytes(tree["app/dr_fallback.py"].content)
    consts = _fallback_consts(tree["app/dr_fallback.py"].content.decode())  # private consts exist only in the source
    assert consts["_F_LATERAL"] == lateral and consts["_FC_INV_LATERAL_TAU"] == floats + params - 2
    assert consts["_RECEIVER_NEO8M"] == 1 and consts["_FC_RECEIVER"] == floats + params - 1
    script = (
        "from array import array\nimport dr_fallback as dr\n"
        "st = array('f', [0.0] * dr.FUSED_STATE_LEN)\nout = array('f', [0.0] * dr.OUT_LEN)\n"
        f"dr.fused_init(st)\nprint(dr.FUSED_STATE_LEN, dr.FIX_AE, st[{consts['_FC_INV_LATERAL_TAU']}])\n"
        "dr.fused_calibrate(st, array('h', [0, 0, 16384, 0, 0, 0] * 50))\n"
        "dr.fused_process(st, array('h', [100, 0, 16384, 0, 0, 30] * 50), array('i', [5000] * 50), out)\n"
        "dr.fused_position(st, 1.0, 0.0, 1.0, 0.0)\ndr.fused_gps(st, 1.0, 0.0)\nprint('ran')\n"
        "try:\n    dr.fused_init(st, dr._FUSED_PARAMS[:-2] + (-1.0, 2.0))\nexcept ValueError as e:\n    print(e)\n"
        "try:\n    dr.fused_init(st, dr._FUSED_PARAMS[:-1] + (3.0,))\nexcept ValueError as e:\n    print(e)\n"
    )
    done = subprocess.run([micropython, "-c", script], capture_output=True, text=True,
                          env=dict(os.environ, MICROPYPATH=str(app)), timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"{L.LAYOUT.fused_buffer_floats + 3} 50 0.5", "ran",
                                        "lateral_tau_s must be >= 0",
                                        "receiver must be one of 0 (neo6m), 1 (neo8m), 2 (other)"]


def _eskf_layout_compiles(tmp_path, layout, monkeypatch) -> subprocess.CompletedProcess:
    """Compile dr_eskf.h against the dr_layout.h `layout` renders, with its checks (DR_ESKF_LAYOUT_CHECKS)."""
    import codegen.generate

    cc = require_tool("cc")
    monkeypatch.setattr(codegen.generate, "LAYOUT", layout)
    native = tmp_path / "native"
    native.mkdir(parents=True)
    for path, f in render_tree(load_board()).items():
        if path.startswith("native/"):
            (native / path[7:]).write_bytes(f.content)
    (native / "check.c").write_text('#include "dr_eskf.h"\nDR_ESKF_LAYOUT_CHECKS\n')
    return subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-pedantic", "-fsyntax-only", "check.c"], cwd=native,
                          capture_output=True, text=True)


def test_eskf_header_is_held_to_the_declaration(tmp_path, monkeypatch):
    """dr_eskf.h writes the filter's structs by hand; the declaration (layout.ESKF) is what dr_native's buffer,
    its exported offsets and hosteskf's cffi structs use. The header compiles against the declaration; a
    declaration that drifts from it (two fields swapped, a field's length, a parameter more) does not, and the
    compiler names the field."""
    assert (done := _eskf_layout_compiles(tmp_path / "same", L.LAYOUT, monkeypatch)).returncode == 0, done.stderr
    eskf = L.ESKF
    state = list(eskf.state)
    at = [f.name for f in state].index("aligned")
    state[at], state[at + 1] = state[at + 1], state[at]
    swapped = dataclasses.replace(L.LAYOUT, eskf=dataclasses.replace(eskf, state=tuple(state)))
    done = _eskf_layout_compiles(tmp_path / "swapped", swapped, monkeypatch)
    assert done.returncode != 0 and "dr_eskf_state_aligned_at" in done.stderr, done.stderr
    longer = dataclasses.replace(eskf, state=tuple(dataclasses.replace(f, length=3) if f.name == "ah" else f
                                                   for f in eskf.state))
    done = _eskf_layout_compiles(tmp_path / "longer", dataclasses.replace(L.LAYOUT, eskf=longer), monkeypatch)
    assert done.returncode != 0 and "dr_eskf_state_ah_at" in done.stderr, done.stderr
    extra = L.Param("extra_sigma", "m", "a parameter the header lacks", L.Store("extra_sigma", "m"), 1.0, gt=0,
                    board=False)
    grown = dataclasses.replace(eskf, params=eskf.params + (extra,))
    done = _eskf_layout_compiles(tmp_path / "grown", dataclasses.replace(L.LAYOUT, eskf=grown), monkeypatch)
    assert done.returncode != 0 and "extra_sigma" in done.stderr, done.stderr


def test_hosteskf_structs_come_from_the_declaration():
    """hosteskf's cffi declarations are rendered from layout.ESKF (not spelled by hand), shaped as the header's."""
    from codegen.kernel import hosteskf

    assert "float mount[3][3];" in hosteskf.CDEF and "float p[23][23];" in hosteskf.CDEF
    assert hosteskf.CONFIG_FIELDS == tuple(f.name for f in L.ESKF.config)
    assert "DR_ESKF_LAYOUT_CHECKS" in hosteskf.C_SOURCE
