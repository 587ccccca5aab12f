# Runs under MicroPython (not collected by pytest): micropython mp_fused_driver.py MODULE INPUT.json
# Drives the fused algorithm of dr_fallback or dr_native as the app does and prints one JSON line: the state after
# fused_init (and the starting state, if given) or after fused_calibrate, then out and the whole fused state after
# every step. Steps: ["p", samples, dt_us] fused_process; ["g", ve, vn, de, dn] fused_position then fused_gps (a fix);
# ["v", ve, vn] fused_gps alone; ["x", ve, vn, de, dn] fused_position alone; ["r", samples] a reset on the road:
# fused_keep, then fused_init, fused_calibrate on the samples and fused_restore of what was kept. With "observe" (per filter, the state
# indices of its covariance) and a module that has the observer hook (dr_fallback), also "observed": [filter, step,
# those values] after every step of every Kalman filter.
import json
import sys
from array import array

dr = __import__(sys.argv[1])
with open(sys.argv[2]) as f:
    data = json.load(f)
st = array("f", [0.0] * dr.FUSED_STATE_LEN)
out = array("f", [0.0] * dr.OUT_LEN)


def _init():
    if "params" in data:
        dr.fused_init(st, data["params"])
    else:
        dr.fused_init(st)


_init()
answer = {"moved": None, "steps": []}
if "observe" in data and hasattr(dr, "_observer"):
    answer["observed"] = []
    entries = data["observe"]

    def _record(buf, which, step):
        answer["observed"].append([which, step, [buf[i] for i in entries[which]]])

    dr._observer = _record
if "state" in data:
    for i, x in enumerate(data["state"]):
        st[i] = x
if data.get("calib") is not None:
    answer["moved"] = dr.fused_calibrate(st, array("h", data["calib"]))
answer["start"] = [st[i] for i in range(data["state_len"])]
for step in data["steps"]:
    kind = step[0]
    if kind == "p":
        dr.fused_process(st, array("h", step[1]), array("i", step[2]), out)
    elif kind == "g":
        dr.fused_position(st, step[1], step[2], step[3], step[4])
        dr.fused_gps(st, step[1], step[2])
    elif kind == "v":
        dr.fused_gps(st, step[1], step[2])
    elif kind == "r":
        kept = array("f", [0.0] * dr.FUSED_KEPT_LEN)
        dr.fused_keep(st, kept)
        _init()
        dr.fused_calibrate(st, array("h", step[1]))
        dr.fused_restore(st, kept)
    else:
        dr.fused_position(st, step[1], step[2], step[3], step[4])
    answer["steps"].append([list(out), [st[i] for i in range(data["state_len"])]])
print(json.dumps(answer))
