"""The fused C kernel (native_ext/dr_fused.c) on the host: compiled with cffi (API mode) from the board's rendered
sources, cached by source hash like codegen.kernel.hostkernel, with a session class the equivalence tests drive exactly as
the app drives dr_native (calibrate, process windows, a GPS update per fix).

    fk = load_fused()                      # default board
    s = fk.session()                       # dr_config + dr_fused_config + dr_fused_state, owned here
    s.calibrate(rest_samples); s.process(samples, dt_us); s.position(ve, vn, de, dn); s.gps(ve, vn); s.state_vector()
"""

from __future__ import annotations

import numpy as np

from codegen.errors import UserError
from codegen.kernel import hostkernel
from codegen.kernel.layout import FUSED

SOURCES = ("dr_kernel.c", "dr_median.c", "dr_geo.c", "dr_fused.c")
HEADERS = ("dr_fused.h",)
PARAM_ORDER = FUSED.param_names  # dr_fused_config_set's order (DR_FUSED_P_*)
STATE_LEN = FUSED.state_floats

CDEF = hostkernel.CONFIG_CDEF + """
typedef struct { ...; } dr_fused_config;
typedef struct { ...; } dr_fused_state;
void dr_fused_config_init(dr_fused_config *cfg);
int dr_fused_config_set(dr_fused_config *cfg, const float *p);
void dr_fused_state_init(dr_fused_state *st);
int dr_fused_calibrate(const dr_config *kcfg, dr_fused_state *st, const int16_t *samples, int32_t count);
void dr_fused_keep(const dr_fused_state *st, float *kept);
void dr_fused_restore(const dr_fused_config *cfg, dr_fused_state *st, const float *kept);
int dr_fused_process(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st, const int16_t *samples,
                     const int32_t *dt_us, int32_t count, float out[6]);
void dr_fused_gps(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn);
void dr_fused_position(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, float de, float dn);
int dr_fused_kf_predict(const dr_fused_config *cfg, dr_fused_state *st);
int dr_fused_kf_update(const dr_fused_config *cfg, dr_fused_state *st, float z0, float z1, const float h[2][3],
                       float r, float x[5]);
int dr_fused_lateral_predict(const dr_fused_config *cfg, dr_fused_state *st, float f2, float f3, float q_speed,
                             float q_leak);
int dr_fused_lateral_correct(const dr_fused_config *cfg, dr_fused_state *st, const float h[4], float r, float y,
                             float x[4]);
int dr_fused_position_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float *phi);
int dr_fused_position_correct(const dr_fused_config *cfg, dr_fused_state *st, float gain[2]);
int dr_fused_speed_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float q_speed, float q_bias);
int dr_fused_speed_correct(const dr_fused_config *cfg, dr_fused_state *st, float r, float gain[2]);
extern "Python+C" void dr_fused_observed(const dr_fused_state *st, int filter, int step);
"""
# the host build observes every filter step (dr_fused.c's DR_FUSED_OBSERVE; nothing on the device)
DEFINES = ("DR_FUSED_OBSERVED",)

C_SOURCE = '#include "dr_fused.h"\n'


class FusedSession:
    """A dr_config, a dr_fused_config and a dr_fused_state, owned here as the app owns them on the device."""

    def __init__(self, fk: "HostFused", params=None):
        self.fk = fk
        ffi, lib = fk.ffi, fk.lib
        self.kcfg = ffi.new("dr_config *")
        lib.dr_config_init(self.kcfg)
        self.cfg = ffi.new("dr_fused_config *")
        if params is None:
            lib.dr_fused_config_init(self.cfg)
        else:
            p = ffi.new("float[%d]" % len(PARAM_ORDER), [float(getattr(params, name)) for name in PARAM_ORDER])
            if lib.dr_fused_config_set(self.cfg, p):
                raise ValueError("a fused time constant is out of range")
        self.st = ffi.new("dr_fused_state *")
        lib.dr_fused_state_init(self.st)
        self.out = ffi.new("float[6]")
        self.observer = None  # set: called as observer(filter, step, state vector) after every filter step

    def observe(self, callback) -> None:
        """Call `callback(filter, step, state)` (DR_FUSED_FILTER_*, DR_FUSED_STEP_*, the state vector then) after
        every step of every Kalman filter in this session, before its covariance is checked; None: stop."""
        self.observer = callback
        address = int(self.fk.ffi.cast("uintptr_t", self.st))
        if callback is None:
            _OBSERVED.pop(address, None)
        else:
            _OBSERVED[address] = self

    def calibrate(self, samples) -> bool:
        raw = np.ascontiguousarray(np.asarray(samples).reshape(-1, 6), dtype=np.int16)
        code = self.fk.lib.dr_fused_calibrate(self.kcfg, self.st, self.fk.ffi.from_buffer("int16_t[]", raw), len(raw))
        if code < 0:
            raise ValueError(f"fused calibration error {code}")
        return code == 1

    def process(self, samples, dt_us) -> np.ndarray:
        ffi = self.fk.ffi
        raw = np.ascontiguousarray(np.asarray(samples).reshape(-1, 6), dtype=np.int16)
        dt = np.ascontiguousarray(np.asarray(dt_us).ravel(), dtype=np.int32)
        if len(dt) != len(raw):
            raise ValueError(f"{len(raw)} samples but {len(dt)} time steps")
        code = self.fk.lib.dr_fused_process(self.kcfg, self.cfg, self.st, ffi.from_buffer("int16_t[]", raw),
                                            ffi.from_buffer("int32_t[]", dt), len(raw), self.out)
        if code:
            raise ValueError(f"fused process error {code}")
        return np.array(list(self.out), dtype=np.float32)

    def position(self, ve: float, vn: float, de: float, dn: float) -> None:
        self.fk.lib.dr_fused_position(self.cfg, self.st, float(ve), float(vn), float(de), float(dn))

    def gps(self, ve: float, vn: float) -> None:
        self.fk.lib.dr_fused_gps(self.cfg, self.st, float(ve), float(vn))

    def keep(self) -> np.ndarray:
        """What a reset should not lose (dr_fused_keep), in codegen/kernel/layout.py's FUSED.kept order."""
        kept = self.fk.ffi.new("float[]", len(FUSED.kept))
        self.fk.lib.dr_fused_keep(self.st, kept)
        return np.array(list(kept), dtype=np.float32)

    def restore(self, kept) -> None:
        values = self.fk.ffi.new("float[]", [float(v) for v in kept])
        self.fk.lib.dr_fused_restore(self.cfg, self.st, values)

    def state_vector(self) -> np.ndarray:
        """The state floats in the order of codegen.kernel.fused.STATE_FIELDS."""
        return np.array(list(self.fk.ffi.cast("float *", self.st)[0:STATE_LEN]), dtype=np.float32)

    def set_state_vector(self, values) -> None:
        f = self.fk.ffi.cast("float *", self.st)
        for i, x in enumerate(np.asarray(values, dtype=np.float64).ravel()):
            f[i] = float(x)


class HostFused:
    def __init__(self, module):
        self.ffi = module.ffi
        self.lib = module.lib
        _attach_observer(module)
        floats = self.ffi.sizeof("dr_fused_state") // self.ffi.sizeof("float")
        if floats != STATE_LEN:  # dr_layout.h asserts its own sizes; this catches sources from another declaration
            raise UserError(f"the compiled dr_fused_state holds {floats} floats, the declaration {STATE_LEN}",
                            hint="regenerate the native sources from codegen/kernel/layout.py")

    def session(self, params=None) -> FusedSession:
        return FusedSession(self, params)


_OBSERVED = {}  # the address of an observed session's state -> the session
_HOOKED = set()  # the compiled modules whose dr_fused_observed is attached


def _attach_observer(module) -> None:
    """The C hook dr_fused_observed, once per compiled module: hands each step to its session's observer."""
    if module.__name__ in _HOOKED:
        return
    ffi = module.ffi

    @ffi.def_extern(name="dr_fused_observed")
    def observed(st, filter_id, step):
        session = _OBSERVED.get(int(ffi.cast("uintptr_t", st)))
        if session is not None and session.observer is not None:
            session.observer(filter_id, step, session.state_vector())

    _HOOKED.add(module.__name__)


def fused_sources(loaded=None) -> dict[str, bytes]:
    return hostkernel.kernel_sources(loaded, extra=("dr_fused.c",) + HEADERS)


def load_fused(loaded=None) -> HostFused:
    """Compile (or find in the cache) the fused kernel for a board (None = the default board)."""
    module, _ = hostkernel.build_module("_drfused", fused_sources(loaded), SOURCES, CDEF, C_SOURCE, DEFINES)
    return HostFused(module)
