"""The ESP32 (xtensawin) dr_native.mpy as `deadreckon build` makes it without Espressif's GCC: Debian's LLVM 22
(codegen.natmod.xtensa_llvm), MicroPython's mpy_ld, the independent verifier (codegen.natmod.verify), and the
module's own code run on qemu-system-xtensa (codegen.natmod.qemu_xtensa: de233_fpu, windowed registers and a
single-precision FPU) with both algorithms on the recorded walk, bit for bit equal to the cffi build of the same C.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from test_natmod_qemu import fused_steps, seed_steps

from codegen.kernel import fused as F
from codegen.natmod import linkmap, mpyfile, qemu_xtensa, verify, xtensa, xtensa_llvm
from codegen.natmod.abi import tree_abi
from codegen.natmod.build import LOG_NAME, build_module
from conftest import mpy_dir, require, require_shared_data, require_tool
from test_kernel_natmod import native_tree

RELEASE = "1.28.0"


def require_llvm():
    for tool in xtensa_llvm.TOOLS:
        require_tool(tool)
    require(not xtensa_llvm.missing_tools(), f"the LLVM route needs {xtensa_llvm.missing_tools()}")
    require(xtensa_llvm.cross_prefix() is not None, f"{xtensa_llvm.COMMAND} is not installed (pip install -e .)")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(module, link map, tree ABI, work folder) of the default board's natmod built by the LLVM route."""
    require_llvm()
    require_tool("make")
    mpy_dir()
    folder = tmp_path_factory.mktemp("xtensawin")
    native = native_tree(folder)
    result = build_module(native, folder / "build", "xtensawin", RELEASE, progress=lambda _: None)
    assert "LLVM" in result.route.name and "relocations verified" in result.checks
    work = folder / "build"
    link = linkmap.parse((work / LOG_NAME).read_text(), work)
    return mpyfile.parse(result.module.read_bytes()), link, tree_abi(result.tree), work


def test_the_verifier_accepts_the_build_and_counts_every_relocated_word(built):
    module, link, abi, _ = built
    report = verify.verify(module, link, abi)
    assert report.l32r_got > 100 and report.l32r_lit > 100 and report.data_words > 10
    assert report.relocations == len(module.relocations) > 50
    assert report.bytes_compared > 0.9 * len(module.text)


def _l32r_sites(module, link):
    sites = []
    for obj in link.objects:
        from elftools.elf.elffile import ELFFile

        with open(obj, "rb") as f:
            elf = ELFFile(f)
            text = next(name for name, _ in linkmap.loaded_sections(obj) if name.startswith(".text"))  # .text.<obj>
            rela = elf.get_section_by_name(".rela" + text)
            base = link.placement(obj, text).addr
            sites += [base + r["r_offset"] for r in rela.iter_relocations()
                      if xtensa.is_l32r(module.text, base + r["r_offset"])]
    return sites


def test_each_objects_sections_have_their_own_name_so_the_got_keeps_their_literals_apart(built):
    """mpy_ld keys a GOT entry for a literal that points into a section by section name and offset, not by file:
    with every object's code in a section called .text, dr_fused.o's static function at .text+0xbb8 and
    dr_kernel.o's at the same offset shared one entry, and half their callers called the other function."""
    _, link, _, _ = built
    names = [p.name for p in link.placements]
    assert len(names) == len(set(names)) and len(link.objects) > 2, names
    sections = [name.split("+")[0] for name, _, _ in link.got.values() if name.startswith((".text", ".data"))]
    assert sections and set(sections) <= set(names)
    assert len({p.obj for p in link.placements if p.name in sections}) > 1  # several objects' literals in the GOT


@pytest.mark.parametrize("which", [0, 57, -1])
def test_one_flipped_l32r_immediate_fails_the_verifier(built, which):
    module, link, abi, _ = built
    sites = _l32r_sites(module, link)
    pc = sites[which]
    text = bytearray(module.text)
    text[pc + 1] ^= 0x01  # imm16 bit 0: the literal one word away
    mutant = dataclasses.replace(module, text=bytes(text))
    with pytest.raises(verify.VerifyError) as failed:
        verify.verify(mutant, link, abi)
    assert "1 wrong target" in str(failed.value) and f"text {pc:#06x}" in str(failed.value)


def test_a_wrong_rodata_pointer_and_a_stray_relocation_fail_the_verifier(built):
    module, link, abi, _ = built
    rodata = bytearray(module.rodata)
    index = next(i for (region, i), dest in module.relocations.items() if region == "rodata" and dest == "text")
    rodata[4 * index] ^= 0x04  # a function object now points 4 bytes into another place
    with pytest.raises(verify.VerifyError, match="the object asks for text"):
        verify.verify(dataclasses.replace(module, rodata=bytes(rodata)), link, abi)
    relocations = dict(module.relocations)
    free = next(i for i in range(len(module.text) // 4 - 1, 0, -1) if ("text", i) not in relocations)
    relocations[("text", free)] = "text"
    with pytest.raises(verify.VerifyError, match="no instruction or pointer asks for it"):
        verify.verify(dataclasses.replace(module, relocations=relocations), link, abi)


def test_llvm_mc_immediates_left_in_place_give_a_module_the_verifier_rejects(built, tmp_path):
    """What the route fixes: llvm-mc's 0xffff in unaligned L32Rs, added to by mpy_ld, loads from 0x30000 below."""
    _, _, abi, work = built
    log = (work / LOG_NAME).read_text()
    objects = linkmap.link_objects(log)
    flags = ["-I", str(work), "-I", str(mpy_dir()), "-std=c99", "-Os", "-DNDEBUG", "-DNO_QSTR",
             "-DMICROPY_ENABLE_DYNRUNTIME", f"-DMP_CONFIGFILE=<{work}/build/dr_native.config.h>",
             "-DMICROPY_FLOAT_IMPL=MICROPY_FLOAT_IMPL_FLOAT"]
    raw = []
    for obj in objects:
        target = tmp_path / obj.name
        xtensa_llvm.compile_object(work / (obj.stem + ".c"), target, flags, clear_l32r=False)
        raw.append(target)
    out = tmp_path / "raw.native.mpy"
    done = subprocess.run([sys.executable, str(mpy_dir() / "tools" / "mpy_ld.py"), "-vvv", "--arch", "xtensawin",
                           "--qstrs", str(work / "build" / "dr_native.config.h"), "-o", str(out),
                           *map(str, raw)], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:]
    link_log = f"LINK\n{sys.executable} mpy_ld.py -o {out} {' '.join(map(str, raw))}\n" + done.stdout
    with pytest.raises(verify.VerifyError) as failed:
        verify.verify(mpyfile.parse(out.read_bytes()), linkmap.parse(link_log, tmp_path), abi)
    assert "outside the GOT" in str(failed.value) and "0xfffd" in str(failed.value)


def test_the_compiler_stand_in_answers_dumpmachine_and_refuses_the_rest_plainly(capsys):
    assert xtensa_llvm.main(["-dumpmachine"]) == 0
    assert capsys.readouterr().out.strip() == "xtensa-esp32-elf"
    assert xtensa_llvm.main(["--print-libgcc-file-name"]) == 1
    assert "LINK_RUNTIME=0" in capsys.readouterr().err
    assert xtensa_llvm.main(["-E", "x.c"]) == 2
    assert "only compiles" in capsys.readouterr().err


def test_the_kernel_uses_no_instruction_de233_fpu_lacks_and_the_binding_is_where_they_are(built):
    """de233_fpu has no MUL32_HIGH (MULUH/MULSH), which -mcpu=esp32 may emit: the kernel must be free of them for
    the run below to be the module's own code; the binding (run on ARM) holds the ones llc emitted."""
    module, link, _, _ = built
    offsets = qemu_xtensa.function_offsets(link)
    sizes = _function_sizes(link)
    kernel = [name for name in offsets if not name.endswith("_fn") and name not in ("mpy_init", "dr_unpack",
                                                                                   "dr_fused_unpack", "dr_raise",
                                                                                   "dr_get_array")]
    assert "dr_fused_process" in kernel and "dr_process" in kernel
    for name in kernel:
        assert not qemu_xtensa.uses_missing(module, offsets[name], offsets[name] + sizes[name]), name
    binding = [found for name in offsets if name.endswith("_fn")
               for found in qemu_xtensa.uses_missing(module, offsets[name], offsets[name] + sizes[name])]
    assert all(m in qemu_xtensa.MISSING_ON_DE233 for _, m in binding)


def _function_sizes(link):
    from elftools.elf.elffile import ELFFile

    sizes = {}
    for obj in link.objects:
        with open(obj, "rb") as f:
            for sym in ELFFile(f).get_section_by_name(".symtab").iter_symbols():
                if sym["st_info"]["type"] == "STT_FUNC":
                    sizes[sym.name] = sym["st_size"]
    return sizes


@pytest.fixture(scope="module")
def walk():
    from codegen.board.loader import load_board
    from codegen.sim.run import build_run

    require_shared_data("gnss-imu-walk")
    board = load_board().board
    return board, build_run("replay-walk", board)


@pytest.fixture(scope="module")
def harness(built, tmp_path_factory):
    require_tool("qemu-system-xtensa")
    _, _, _, work = built
    return qemu_xtensa.build_harness(work, mpy_dir(), tmp_path_factory.mktemp("harness"))


def test_esp32_code_runs_the_seed_kernel_bit_for_bit_like_cffi(built, harness, walk):
    from codegen.kernel.hostkernel import load_kernel

    module, link, _, _ = built
    board, run = walk
    steps = seed_steps(board, run)
    answers = qemu_xtensa.run(module, link, harness, steps, "seed", 10)
    c = load_kernel().session()
    assert bool(answers[0].out[0]) == c.calibrate(steps[0][1])
    np.testing.assert_array_equal(answers[0].state[:4], c.q)
    for (_, samples, dt), got in zip(steps[1:], answers[1:]):
        d, v, _ = c.process(samples, dt)
        assert np.array_equal(got.out, np.concatenate([d, v])), (got.out, d, v)
        assert np.array_equal(got.state[:4], c.q) and np.array_equal(got.state[4:7], c.v)
    assert np.linalg.norm(answers[-1].out[:3]) > 1.0
    assert all(50_000 < a.instructions < 5_000_000 for a in answers[1:])  # ICOUNT counted the window


def test_esp32_code_runs_the_fused_algorithm_bit_for_bit_like_cffi(built, harness, walk):
    from codegen.kernel.hostfused import load_fused

    module, link, _, _ = built
    _, run = walk
    steps = fused_steps(run)
    answers = qemu_xtensa.run(module, link, harness, steps, "fused", F.STATE_LEN)
    c = load_fused().session()
    assert bool(answers[0].out[0]) == c.calibrate(steps[0][1])
    for item, got in zip(steps[1:], answers[1:]):
        if item[0] == "P":
            assert np.array_equal(got.out, c.process(item[1], item[2]))
        else:
            c.position(*item[1:])
            c.gps(item[1], item[2])
        want = c.state_vector()
        differ = np.flatnonzero(got.state.view(np.uint32) != want.view(np.uint32))
        assert differ.size == 0, [(F.STATE_FIELDS[i], got.state[i], want[i]) for i in differ[:5]]
    assert np.hypot(*answers[-1].state[F.IDX["pe"]:F.IDX["pn"] + 1]) > 5.0
