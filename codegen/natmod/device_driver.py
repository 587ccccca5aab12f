# Runs on MicroPython (the QEMU port), not on the host: drives one algorithm of dr_native or dr_fallback the way the
# app calls it, with arrays the host sends (codegen.natmod.windows), and prints one line per call:
# "R <clock counts of the call> <hex of out and the state, float32 little-endian>".
import binascii
from array import array


class Runner:
    def __init__(self, dr, algorithm, clock, state_floats):
        self.dr, self.algorithm, self.clock, self.state_floats = dr, algorithm, clock, state_floats
        self.out = array("f", [0.0] * dr.OUT_LEN)
        if algorithm == "seed":
            self.state = array("f", [0.0] * dr.STATE_LEN)
            dr.init(self.state)
        else:
            self.state = array("f", [0.0] * dr.FUSED_STATE_LEN)
            dr.fused_init(self.state)
        t0 = clock()
        self.overhead = clock() - t0  # what reading the clock itself costs

    def calibrate(self, samples):
        dr, st = self.dr, self.state
        t0 = self.clock()
        moved = dr.calibrate(st, samples) if self.algorithm == "seed" else dr.fused_calibrate(st, samples)
        t1 = self.clock()
        self.out[0] = moved  # the verdict, where the host reads it
        self.report(t0, t1)

    def window(self, samples, dt):
        dr, st = self.dr, self.state
        t0 = self.clock()
        if self.algorithm == "seed":
            dr.process(st, samples, dt, self.out)
        else:
            dr.fused_process(st, samples, dt, self.out)
        t1 = self.clock()
        self.report(t0, t1)

    def fix(self, gps):
        dr, st = self.dr, self.state
        ve, vn, de, dn = gps[0], gps[1], gps[2], gps[3]
        t0 = self.clock()
        dr.fused_position(st, ve, vn, de, dn)
        dr.fused_gps(st, ve, vn)
        t1 = self.clock()
        self.report(t0, t1)

    def report(self, t0, t1):
        result = bytes(self.out) + bytes(memoryview(self.state)[0:self.state_floats])
        print("R", (t1 - t0 - self.overhead) & 0xFFFFFFFF, binascii.hexlify(result).decode())
