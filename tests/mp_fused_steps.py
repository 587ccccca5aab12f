# Runs under MicroPython (not collected by pytest): micropython mp_fused_steps.py INPUT.json
# Each case {"fn", "state", "args"}: dr_fallback's state buffer (fused_init's, then the case's state floats over its
# first ones; a value not finite comes as its string: "nan", "inf"), the step dr_fallback.<fn>(buffer, *args) run on
# it; prints one JSON line: per case the state floats after the step and what it returned.
import json
import sys
from array import array

import dr_fallback as dr

with open(sys.argv[1]) as f:
    data = json.load(f)
st = array("f", [0.0] * dr.FUSED_STATE_LEN)
answer = []
for case in data["cases"]:
    dr.fused_init(st)
    for i, x in enumerate(case["state"]):
        st[i] = float(x) if isinstance(x, str) else x
    if case["fn"] == "fused_keep":  # what it copies out is its answer
        kept = array("f", [0.0] * dr.FUSED_KEPT_LEN)
        dr.fused_keep(st, kept)
        returned = list(kept)
    else:
        returned = getattr(dr, case["fn"])(st, *case["args"])
    if isinstance(returned, tuple):
        returned = list(returned)
    answer.append([[st[i] for i in range(len(case["state"]))], returned])
print(json.dumps(answer))
