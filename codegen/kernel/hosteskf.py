"""The error-state filter's C port (native_ext/dr_eskf.c) on the host: compiled with cffi (API mode) from the board's
rendered sources, cached by source hash like codegen.kernel.hostkernel, with a session the equivalence tests drive
as codegen.kernel.eskf's reference is driven (calibrate, process samples, a GPS fix), and the benchmark method
"eskf-c" (`estimate`, the contract of codegen.sim.methods).

    ek = load_eskf()
    s = ek.session(EskfConfig())          # dr_config + dr_eskf_config + dr_eskf_state, owned here
    s.calibrate(rest_counts); s.process(counts, dt_us); s.gps(t, enu, vel_en); s.st.pos[0]
"""

from __future__ import annotations

import numpy as np

from codegen.kernel import eskf, hostkernel
from codegen.kernel.eskf import N_ERR, EskfConfig
from codegen.kernel.layout import ESKF

SOURCES = ("dr_kernel.c", "dr_median.c", "dr_geo.c", "dr_eskf.c")
HEADERS = ("dr_eskf.h",)
CONFIG_FIELDS = tuple(f.name for f in ESKF.config)  # EskfConfig's names, in dr_eskf_config's order


def _members(fields_) -> str:
    """The struct members of a codegen.kernel.layout declaration, as C (float m[3][3] for a shaped field)."""
    out = []
    for f in fields_:
        dims = "".join(f"[{d}]" for d in (f.shape or ((f.length,) if f.length > 1 else ())))
        out.append(f"{f.ctype} {f.name}{dims};")
    return " ".join(out)


# The structs as codegen/kernel/layout.py declares them (dr_eskf.h writes them by hand; DR_ESKF_LAYOUT_CHECKS,
# compiled into this module, holds the header to the same declaration, field by field).
CDEF = hostkernel.CONFIG_CDEF + f"""
typedef struct {{ {_members(ESKF.config)} ...; }} dr_eskf_config;
typedef struct {{ {_members(ESKF.state)} ...; }} dr_eskf_state;
""" + """
void dr_eskf_config_init(dr_eskf_config *cfg);
void dr_eskf_state_init(dr_eskf_state *st);
int dr_eskf_calibrate(const dr_config *kcfg, const dr_eskf_config *cfg, dr_eskf_state *st, const int16_t *samples,
                      int32_t count);
int dr_eskf_process(const dr_config *kcfg, const dr_eskf_config *cfg, dr_eskf_state *st, const int16_t *samples,
                    const int32_t *dt_us, int32_t count, float out[6]);
void dr_eskf_calibration_interval(dr_eskf_state *st, float ve, float vn, float seconds);
int dr_eskf_gps(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                float vn);
void dr_eskf_propagate_covariance(const dr_eskf_config *cfg, dr_eskf_state *st);
int dr_eskf_scalar_update(float p[23][23], float dx[23], const int32_t *h_index, const float *h_value, int32_t nnz,
                          float y, float r);
void dr_eskf_nhc_rows(const dr_eskf_state *st, float h[2][23], float predicted[2]);
int dr_eskf_covariance_usable(const float p[23][23]);
void dr_eskf_prior(const dr_eskf_config *cfg, dr_eskf_state *st);
extern "Python+C" void dr_eskf_observed(const dr_eskf_state *st, int step);
"""
DEFINES = ("DR_ESKF_OBSERVED",)  # the host build hands every covariance step to Python (nothing on the device)
C_SOURCE = '#include "dr_eskf.h"\nDR_ESKF_LAYOUT_CHECKS\n'
STEPS = ("prior", "predict", "update")  # DR_ESKF_STEP_*


class EskfSession:
    """A dr_config (the board's axis map and scales), a dr_eskf_config and a dr_eskf_state, owned here."""

    def __init__(self, ek: "HostEskf", cfg: EskfConfig | None = None):
        self.ek = ek
        ffi, lib = ek.ffi, ek.lib
        self.kcfg = ffi.new("dr_config *")
        lib.dr_config_init(self.kcfg)
        self.cfg = ffi.new("dr_eskf_config *")
        lib.dr_eskf_config_init(self.cfg)
        for name in CONFIG_FIELDS:
            setattr(self.cfg, name, float(getattr(cfg if cfg is not None else EskfConfig(), name)))
        self.st = ffi.new("dr_eskf_state *")
        lib.dr_eskf_state_init(self.st)
        self.out = ffi.new("float[6]")
        self.observer = None

    def use_kernel_config(self, kcfg) -> None:
        """The axis map, scales and motion limit of a codegen.kernel.reference.KernelConfig (a run's board)."""
        for i, (source, sign) in enumerate(kcfg.axis_map):
            self.kcfg.axis_source[i] = int(source)
            self.kcfg.axis_sign[i] = float(sign)
        self.kcfg.accel_ms2_per_lsb = kcfg.accel_ms2_per_lsb
        self.kcfg.gyro_rads_per_lsb = kcfg.gyro_rads_per_lsb
        self.kcfg.motion_limit_lsb2 = (kcfg.motion_threshold_g * kcfg.accel_lsb_per_g) ** 2

    def observe(self, callback) -> None:
        """Call `callback(step, P)` ("prior", "predict", "update"; P as a float64 copy of the float32 matrix) after
        every covariance step of this session, before it is checked; None: stop."""
        self.observer = callback
        address = int(self.ek.ffi.cast("uintptr_t", self.st))
        if callback is None:
            _OBSERVED.pop(address, None)
        else:
            _OBSERVED[address] = self

    def calibrate(self, counts) -> bool:
        raw = np.ascontiguousarray(np.asarray(counts).reshape(-1, 6), dtype=np.int16)
        code = self.ek.lib.dr_eskf_calibrate(self.kcfg, self.cfg, self.st, self.ek.ffi.from_buffer("int16_t[]", raw),
                                             len(raw))
        if code < 0:
            raise ValueError(f"eskf calibration error {code}")
        return code == 1

    def process(self, counts, dt_us) -> np.ndarray:
        ffi = self.ek.ffi
        raw = np.ascontiguousarray(np.asarray(counts).reshape(-1, 6), dtype=np.int16)
        dt = np.ascontiguousarray(np.asarray(dt_us).ravel(), dtype=np.int32)
        if len(dt) != len(raw):
            raise ValueError(f"{len(raw)} samples but {len(dt)} time steps")
        self.ek.lib.dr_eskf_process(self.kcfg, self.cfg, self.st, ffi.from_buffer("int16_t[]", raw),
                                    ffi.from_buffer("int32_t[]", dt), len(raw), self.out)
        return np.array(list(self.out))

    def calibration_interval(self, vel_en, seconds: float) -> None:
        self.ek.lib.dr_eskf_calibration_interval(self.st, float(vel_en[0]), float(vel_en[1]), float(seconds))

    def gps(self, t_s: float, enu, vel_en) -> bool:
        return bool(self.ek.lib.dr_eskf_gps(self.cfg, self.st, float(t_s), float(enu[0]), float(enu[1]),
                                            float(enu[2]), float(vel_en[0]), float(vel_en[1])))

    def set_from_reference(self, ref) -> None:
        """This state <- a codegen.kernel.eskf.EskfState (rounded to float32)."""
        st = self.st
        for name, value in _vector_fields(ref).items():
            for i, x in enumerate(value):
                getattr(st, name)[i] = float(x)
        for name in ("acc_t", "sat_dv", "since_nhc", "mean_f", "var_f", "rest_s", "rate2", "gps_speed", "t_fix",
                     "cov_repairs"):
            setattr(st, name, float(getattr(ref, name)))
        st.aligned = 1.0 if ref.aligned else 0.0
        st.gyro_moving = 1.0 if ref.gyro_moving else 0.0
        st.al_have_prev = 0.0 if ref.al_prev is None else 1.0
        for i in range(2):
            st.al_du[i] = float(ref.al_du[i])
            st.al_u[i] = float(ref.al_u[i])
            st.al_s[i] = float(ref.al_s[i])
            st.al_prev[i] = 0.0 if ref.al_prev is None else float(ref.al_prev[i])
        for i, x in enumerate(ref.al_sums):
            st.al_sums[i] = float(x)
        for name, value in (("mount", ref.c), ("acc_a", ref.acc_a), ("acc_b", ref.acc_b), ("p", ref.p)):
            target = getattr(st, name)
            for i in range(value.shape[0]):
                for j in range(value.shape[1]):
                    target[i][j] = float(value[i, j])

    def nominal(self) -> dict[str, np.ndarray]:
        """pos, vel, q, bg, ba, sg, ge and mount as float64 arrays, for comparison with the reference."""
        st = self.st
        out = {name: np.array(list(getattr(st, name))) for name in ("pos", "vel", "q", "bg", "ba", "sg", "ge")}
        out["mount"] = np.array([list(row) for row in st.mount])
        return out

    def covariance(self) -> np.ndarray:
        return matrix(self.ek.ffi, self.st.p)

    def copy(self) -> "EskfSession":
        other = EskfSession.__new__(EskfSession)
        other.ek, other.kcfg, other.cfg, other.observer = self.ek, self.kcfg, self.cfg, None
        other.st = self.ek.ffi.new("dr_eskf_state *", self.st[0])
        other.out = self.ek.ffi.new("float[6]")
        return other


def _vector_fields(ref) -> dict[str, tuple]:
    return {"pos": (ref.pe, ref.pn, ref.pu), "vel": (ref.ve, ref.vn, ref.vu), "q": (ref.qw, ref.qx, ref.qy, ref.qz),
            "bg": (ref.bgx, ref.bgy, ref.bgz), "ba": (ref.bax, ref.bay, ref.baz), "sg": (ref.sgx, ref.sgy, ref.sgz),
            "ge": (ref.gee, ref.gen, ref.geu), "ws": (ref.wsx, ref.wsy, ref.wsz), "ah": (ref.ahe, ref.ahn),
            "acc_dv": tuple(ref.acc_dv)}


def reference_nominal(ref) -> dict[str, np.ndarray]:
    """EskfSession.nominal's fields of a codegen.kernel.eskf.EskfState."""
    out = {name: np.array(v, dtype=np.float64) for name, v in _vector_fields(ref).items()
           if name in ("pos", "vel", "q", "bg", "ba", "sg", "ge")}
    out["mount"] = np.array(ref.c, dtype=np.float64)
    return out


def matrix(ffi, p) -> np.ndarray:
    """A C float[23][23] as a float64 array."""
    return np.frombuffer(ffi.buffer(p, 4 * N_ERR * N_ERR), dtype=np.float32).reshape(N_ERR, N_ERR).astype(np.float64)


class HostEskf:
    def __init__(self, module):
        self.ffi = module.ffi
        self.lib = module.lib
        _attach_observer(module)

    def session(self, cfg: EskfConfig | None = None) -> EskfSession:
        return EskfSession(self, cfg)


_OBSERVED = {}  # the address of an observed session's state -> the session
_HOOKED = set()


def _attach_observer(module) -> None:
    if module.__name__ in _HOOKED:
        return
    ffi = module.ffi

    @ffi.def_extern(name="dr_eskf_observed")
    def observed(st, step):
        session = _OBSERVED.get(int(ffi.cast("uintptr_t", st)))
        if session is not None and session.observer is not None:
            session.observer(STEPS[step], matrix(ffi, st.p))

    _HOOKED.add(module.__name__)


def eskf_sources(loaded=None) -> dict[str, bytes]:
    return hostkernel.kernel_sources(loaded, extra=("dr_eskf.c",) + HEADERS)


def load_eskf(loaded=None) -> HostEskf:
    """Compile (or find in the cache) the filter's C for a board (None = the default board)."""
    module, _ = hostkernel.build_module("_dreskf", eskf_sources(loaded), SOURCES, CDEF, C_SOURCE, DEFINES)
    return HostEskf(module)


# --------------------------------------------------------------------------------------------- the benchmark method
def _pass(run, cfg: EskfConfig):
    """As codegen.kernel.eskf._pass, through the C: (t, dt_us, snapshots: fix index -> (sample index, session))."""
    from codegen.kernel.reference import KernelConfig

    session = load_eskf().session(cfg)
    session.use_kernel_config(KernelConfig.from_board(run.board))
    t = run.t_us * 1e-6
    dt_us = np.diff(run.t_us).astype(np.int32)
    n_cal = int(np.searchsorted(t, run.board.algorithm.calibration_s))
    session.calibrate(run.counts[:n_cal])
    gps = run.gps
    vel = gps.device_velocity()
    spanning = eskf.calibration_fix(gps, float(t[0]), float(t[n_cal]))
    if spanning is not None:
        session.calibration_interval(vel[spanning], float(t[n_cal] - gps.t[spanning]))
    snaps = {}
    k = n_cal
    for j in np.flatnonzero(gps.valid & (gps.t >= t[n_cal])):
        stop = min(int(np.searchsorted(t, gps.t[j], side="left")), len(dt_us))
        if stop > k:
            session.process(run.counts[k:stop], dt_us[k:stop])
            k = stop
        session.gps(float(gps.t[j]), gps.enu[j], vel[j])
        snaps[int(j)] = (k, session.copy())
    return t, dt_us, snaps


def estimate(run, starts, times, cfg: EskfConfig | None = None):
    """The method "eskf-c": codegen.kernel.eskf.estimate with the filter in float32 C."""
    cfg = EskfConfig() if cfg is None else cfg
    key = ("eskf_c_pass", cfg)
    if key not in run.cache:
        run.cache[key] = _pass(run, cfg)
    t, dt_us, snaps = run.cache[key]
    idx = run.gps.last_valid_before(starts)
    vel = run.gps.device_velocity()
    out = np.empty(times.shape + (2,))
    for i, j in enumerate(idx):
        k, snap = snaps[int(j)]
        if snap.st.aligned == 0.0:
            out[i] = run.gps.enu[j, :2] + vel[j] * (times[i] - run.gps.t[j])[:, None]
            continue
        s = snap.copy()
        s.st.gps_speed = 0.0
        ends = np.searchsorted(t, times[i], side="right") - 1
        for h, end in enumerate(ends):
            end = min(int(end), len(dt_us))
            if end > k:
                s.process(run.counts[k:end], dt_us[k:end])
                k = end
            out[i, h] = (s.st.pos[0], s.st.pos[1])
    return out
