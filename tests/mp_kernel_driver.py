# Runs under MicroPython (not collected by pytest): micropython mp_kernel_driver.py MODULE INPUT.json
# Feeds the kernel test vectors through dr_fallback or dr_native and prints one JSON line with the results.
import json
import sys
from array import array

dr = __import__(sys.argv[1])
with open(sys.argv[2]) as f:
    data = json.load(f)

answer = {"module": sys.argv[1], "cases": [], "medians": [], "latlon": []}
for case in data["cases"]:
    cfg = case["config"]
    state = array("f", [0.0] * dr.state_len(cfg[0]))
    out = array("f", [0.0] * dr.OUT_LEN)
    dr.init(state, cfg[0], cfg[1], cfg[2], cfg[3], cfg[4], cfg[5])
    moved = None
    calibrated = None
    if case["calib"] is not None:
        moved = dr.calibrate(state, array("h", case["calib"]))
        calibrated = [state[dr.Q + i] for i in range(4)] + [state[dr.GYRO_BIAS + i] for i in range(3)]
    else:
        for i in range(4):
            state[dr.Q + i] = case["q0"][i]
        for i in range(3):
            state[dr.GYRO_BIAS + i] = case["bias"][i]
    dr.set_velocity(state, case["v0"][0], case["v0"][1], case["v0"][2])
    windows = []
    for samples, dt in case["windows"]:
        dr.process(state, array("h", samples), array("i", dt), out)
        windows.append([list(out), [state[dr.Q + i] for i in range(4)]])
    answer["cases"].append({"moved": moved, "calibrated": calibrated, "windows": windows})
for values, b in data["medians"]:
    buf = array("f", values)
    out = array("f", [0.0] * (len(values) // b))
    dr.block_median(buf, b, out)
    answer["medians"].append(list(out))
for lat, lon, east, north in data.get("latlon", []):
    answer["latlon"].append(list(dr.offset_latlon(lat, lon, east, north)))
print(json.dumps(answer))
