"""The CircuitPython app's seed kernel takes its block medians from ulab (CircuitPython's own unix port, which has
it): the same medians as the pure-Python Shell sort and as numpy.median within CircuitPython's 30-bit rounding.
benchmarks/circuitpython.py ulab prints the speed that decided it."""

from __future__ import annotations

import json

import numpy as np

from codegen.sim.harness import generate_app, run_script
from conftest import circuitpython

EPS30 = 2.0**-22
PROBE = r"""
import json
import sys
from array import array
import dr_fallback as dr

blocks = json.loads(open(sys.argv[1]).read())
out = []
for values in blocks:
    x = array("f", values)
    fast = dr._block_median(x, 0, len(values))
    assert list(x) == list(array("f", values))  # ulab leaves the buffer as it was
    out.append([fast, dr._median(x, 0, len(values)), dr._np is not None])
print(json.dumps(out))
"""


def test_ulab_block_medians_equal_the_pure_python_ones(tmp_path):
    yaml = tmp_path / "seed.yaml"
    yaml.write_text("extends: pico-gy521-circuitpython\nname: seed\nalgorithm: {mode: seed}\n")
    lib = generate_app(yaml, tmp_path / "out") / "app" / "lib"
    rng = np.random.default_rng(5)
    blocks = [rng.normal(0.0, 3.0, n).astype(np.float32) for n in (16, 16, 15, 8, 1, 2, 64)]
    blocks.append(np.full(16, 9.80665, np.float32))  # a block of equal values: exact
    (tmp_path / "blocks.json").write_text(json.dumps([[float(v) for v in b] for b in blocks]))
    (tmp_path / "probe.py").write_text(PROBE)
    done = run_script(circuitpython(), lib, str(tmp_path / "probe.py"), [str(tmp_path / "blocks.json")], timeout=60)
    assert done.returncode == 0, done.stderr + done.stdout
    for block, (fast, pure, has_ulab) in zip(blocks, json.loads(done.stdout)):
        assert has_ulab
        want = float(np.median(block.astype(np.float64)))
        scale = float(np.abs(block).max())
        assert abs(fast - pure) <= 2 * EPS30 * scale and abs(fast - want) <= 2 * EPS30 * scale, (fast, pure, want)
