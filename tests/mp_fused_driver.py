# Runs under MicroPython (not collected by pytest): micropython mp_fused_driver.py MODULE INPUT.json
# Drives the fused algorithm of dr_fallback or dr_native as the app does (calibrate, windows, one GPS update per fix)
# and prints one JSON line: the calibration verdict and, after every step, out and the whole fused state.
import json
import sys
from array import array

dr = __import__(sys.argv[1])
with open(sys.argv[2]) as f:
    data = json.load(f)
st = array("f", [0.0] * dr.FUSED_STATE_LEN)
out = array("f", [0.0] * dr.OUT_LEN)
if "params" in data:
    dr.fused_init(st, data["params"])
else:
    dr.fused_init(st)
answer = {"moved": dr.fused_calibrate(st, array("h", data["calib"])), "steps": []}
for step in data["steps"]:
    if step[0] == "p":
        dr.fused_process(st, array("h", step[1]), array("i", step[2]), out)
    else:
        dr.fused_position(st, step[1], step[2], step[3], step[4])
        dr.fused_gps(st, step[1], step[2])
    answer["steps"].append([list(out), [st[i] for i in range(data["state_len"])]])
print(json.dumps(answer))
