"""One declaration of the kernels' memory: the state fields, the configuration slots (with units and limits), the
flags and the return codes of the seed kernel (C prefix `dr`) and of the fused method (`dr_fused`).

Rendered, never copied by hand, into
- the C header `native/dr_layout.h` (templates/native/dr_layout.h.j2): the structs, their lengths and the offsets
  of their fields, the parameter checks and the parameters' conversion into the configuration the loop reads;
- the board constants `native/dr_board.h` (the fused parameters' board values);
- the MicroPython fallback `app/dr_fallback.py` (templates/micropython/dr_fallback.py.j2): the offsets as `const()`,
  the lengths, the board's parameters and the same checks and conversions;
and read by the float64 reference (codegen/kernel/fused.py: FusedConfig, FusedState, STATE_FIELDS), the board model
(codegen/board/model.py: one key `algorithm.fused_<name>` per fused parameter, with its default, unit and limits) and
the board rules (a parameter `at_most` another). The arithmetic of every step stays hand-written in each language.

Adding a state field is one `Field(...)` line here plus the algorithm's lines; adding a parameter is one
`Param(...)` line plus the algorithm's lines (docs/kernel-layout.md says where those go).

Every field is 4 bytes (float or int32), so a struct is also a run of floats in a caller's array('f'): offsets are
counted in floats. The order here is the order in memory; the fields the app reads (`public`) keep their offsets.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Union

Number = Union[float, int, bool]

# Named constants a conversion may multiply by, with their values: DR_<NAME> in C (dr_math.h), _<NAME> in the
# fallback (dr_fallback.py).
CONSTANTS = {"GRAVITY_MS2": 9.80665, "RAD_PER_DEG": 0.017453292519943295, "RAD_PER_CYCLE": 6.283185307179586}


@dataclass(frozen=True)
class Field:
    """A state or configuration field: `length` 4-byte values (`ctype` float or int32_t)."""

    name: str  # the C struct member; the reference's attribute when length is 1
    unit: str
    doc: str
    length: int = 1
    elements: tuple[str, ...] = ()  # the reference's attribute of each value when length > 1 (default name0..)
    initial: tuple[float, ...] = ()  # values after *_state_init, from the first element (the rest 0)
    ctype: str = "float"  # "float" or "int32_t"
    public: str = ""  # the name under which dr_native and dr_fallback export the offset ("" = private)
    # the fallback's fused_process keeps it in locals named as its elements through the per-sample loop, loaded
    # before it: "read" (the loop does not change it), "carry" (and stored back after it); "" = in the buffer
    local: str = ""
    group: str = ""  # the concern this field opens in memory order (a heading in the C struct)
    shape: tuple[int, ...] = ()  # the C array's dimensions when it has more than one ((3, 3): float m[3][3])

    def element_names(self) -> tuple[str, ...]:
        if self.length == 1:
            return (self.name,)
        return self.elements or tuple(f"{self.name}{k}" for k in range(self.length))


@dataclass(frozen=True)
class Store:
    """How a parameter is kept in the configuration struct the loop reads: `field = form(value)` with
      copy  value                       scale  value * factor
      recip factor / value (value > 0)  rate   1 / value, or 0 when value is 0 (a time constant of 0 = off)
      square times * (value * factor)^2
    factor: a name of CONSTANTS, another parameter's name, or None (1)."""

    field: str
    unit: str
    form: str = "copy"
    factor: Optional[str] = None
    times: float = 1.0


@dataclass(frozen=True)
class Param:
    """A configuration slot as the caller sets it (board key, dr_*_config_set argument), in the unit it is given in.
    Limits: gt/ge/le as in pydantic; at_most: another parameter's name it may not exceed; multiple_of: another
    (integer) parameter's name it must be a positive multiple of. A failed check returns DR_<error>.
    kind "choice": the board key takes one of `choices` (strings), the kernels its index (0, 1, ...), named
    <C_PREFIX>_<NAME>_<CHOICE> in C and _<NAME>_<CHOICE> in the fallback."""

    name: str
    unit: str
    doc: str
    store: Store
    default: Optional[Number] = None  # the board's default (None: the board model declares the key itself)
    kind: str = "float"  # "float", "int" (int32_t in C), "bool" (0.0 / 1.0) or "choice" (the index of one of choices)
    gt: Optional[float] = None
    ge: Optional[float] = None
    le: Optional[float] = None
    at_most: Optional[str] = None
    at_most_why: str = ""  # the board rule's message, formatted with value, limit and unit
    multiple_of: Optional[str] = None
    error: str = "ERR_RANGE"
    choices: tuple[str, ...] = ()
    board: bool = True  # False: no board key; the kernel keeps `default` (a cadence its tests were run at)

    def limits_text(self) -> str:
        """The limits in words, for error messages: '> 0', '>= 0 and <= 1', 'a positive multiple of block'."""
        if self.kind == "choice":
            return "one of " + ", ".join(f"{i} ({name})" for i, name in enumerate(self.choices))
        parts = []
        if self.multiple_of:
            parts.append(f"a positive multiple of {self.multiple_of}")
        for symbol, bound in (("> ", self.gt), (">= ", self.ge), ("<= ", self.le)):
            if bound is not None and not (self.multiple_of and symbol == ">= "):
                parts.append(f"{symbol}{bound:g}")
        if self.at_most:
            parts.append(f"<= {self.at_most}")
        return " and ".join(parts)

    @property
    def ctype(self) -> str:
        """The C type of the argument (a parameter array holds floats whatever the kind)."""
        return "int32_t" if self.kind == "int" else "float"

    @property
    def checked(self) -> bool:
        """Whether the kernels check the value (a bool is any value: 0 or not)."""
        return self.kind == "choice" or any(x is not None for x in (self.gt, self.ge, self.le, self.at_most,
                                                                    self.multiple_of))

    def number(self, value) -> float:
        """The value as a kernel parameter (a float; a bool is 1.0 or 0.0; a choice its index)."""
        return float(self.choices.index(value)) if self.kind == "choice" else float(value)

    def code(self, choice: str) -> int:
        """A choice's index, the number the kernels compare the parameter with."""
        return self.choices.index(choice)


@dataclass(frozen=True)
class Flag:
    name: str
    value: int
    doc: str


@dataclass(frozen=True)
class Code:
    name: str
    value: int
    doc: str


@dataclass(frozen=True)
class Kernel:
    """One kernel's memory. C names: `<c_prefix>_state`, `<c_prefix>_config`, macros `<C_PREFIX>_...`; the fallback's
    offsets `<py_prefix>_<FIELD>`. The configuration struct holds each parameter's stored field, in parameter order,
    then `config_extra` (fields only *_config_init sets, from the board)."""

    title: str
    c_prefix: str
    py_prefix: str
    state: tuple[Field, ...]
    params: tuple[Param, ...]
    config_extra: tuple[Field, ...] = ()
    flags: tuple[Flag, ...] = ()
    board_prefix: str = ""  # the board keys of the parameters: algorithm.<board_prefix><name> ("" = not generated)
    param_array: bool = False  # C: *_config_set takes the parameters as one float array (else as arguments)
    # the state values a reset should not lose, by element name, in the order *_keep copies them out (the fallback's
    # and the C's offset tables are rendered from it; the reference reads it)
    kept: tuple[str, ...] = ()

    @property
    def macro(self) -> str:
        return self.c_prefix.upper()

    @property
    def config(self) -> tuple[Field, ...]:
        stored = tuple(
            Field(p.store.field, p.store.unit, f"from {p.name}" + (f" ({p.unit})" if p.unit else ""),
                  ctype=p.ctype)
            for p in self.params
        )
        return stored + self.config_extra

    @property
    def state_floats(self) -> int:
        return sum(f.length for f in self.state)

    @property
    def config_floats(self) -> int:
        return sum(f.length for f in self.config)

    def offsets(self, fields: tuple[Field, ...]) -> dict[str, int]:
        """Field name -> offset in floats from the start of its struct."""
        out, at = {}, 0
        for f in fields:
            out[f.name] = at
            at += f.length
        return out

    @property
    def state_offsets(self) -> dict[str, int]:
        return self.offsets(self.state)

    @property
    def config_offsets(self) -> dict[str, int]:
        return self.offsets(self.config)

    def element_names(self) -> tuple[str, ...]:
        """Every state value's name, in memory order (the reference's flat view)."""
        return tuple(name for f in self.state for name in f.element_names())

    def element_offsets(self) -> dict[str, int]:
        return {name: i for i, name in enumerate(self.element_names())}

    def named_elements(self) -> tuple[tuple[Field, int, str], ...]:
        """(field, index, name) of every element an array field names (`elements`): the C index constant
        `<C_PREFIX>_<NAME>` into the field (st->p[DR_FUSED_P22]), the fallback's offset `<py_prefix>_<NAME>`."""
        return tuple((f, i, name) for f in self.state if f.elements for i, name in enumerate(f.elements))

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def field(self, name: str) -> Field:
        for f in self.state:
            if f.name == name:
                return f
        raise KeyError(name)

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    def board_key(self, p: Param) -> str:
        return self.board_prefix + p.name

    @property
    def kept_offsets(self) -> tuple[int, ...]:
        """The offsets in floats of the values a reset should not lose (`kept`), in their order."""
        at = self.element_offsets()
        return tuple(at[name] for name in self.kept)

    def initial_values(self) -> tuple[tuple[Field, int, float], ...]:
        """(field, element index, value) of every non-zero value after *_state_init."""
        return tuple((f, i, float(v)) for f in self.state for i, v in enumerate(f.initial) if v)


# The fused method's Kalman filters and the steps after which each one's covariance is checked (and, on the host,
# observed): DR_FUSED_FILTER_* / DR_FUSED_STEP_* in C, _FILTER_* / _STEP_* in the fallback, FILTER_* / STEP_* in
# codegen.kernel.fused.
COVARIANCE_FILTERS = ("TILT", "LATERAL", "POSITION", "SPEED")
FILTER_STEPS = ("START", "PREDICT", "UPDATE")

RETURN_CODES = (
    Code("OK", 0, "done"),
    Code("MOVED", 1, "calibration: an accel axis' standard deviation exceeded the motion threshold"),
    Code("ERR_BLOCK", -1, "block < 1 (or, fused, longer than the median option's ring)"),
    Code("ERR_WINDOW", -2, "window < 1 or not a multiple of block"),
    Code("ERR_COUNT", -3, "sample count < 1 or not a multiple of block"),
    Code("ERR_RANGE", -4, "a parameter outside its limits, or (dr_calibrate, dr_process) an unusable configuration: "
         "block < 1 or an axis source outside 0..2"),
)
OUT_FLOATS = 6  # floats *_process writes: displacement East, North, Up (m), velocity East, North, Up (m/s)
FUSED_MEDIAN_MAX = 32  # samples: the longest block the fused median option's ring keeps

SEED = Kernel(
    title="the seed kernel (dr_kernel.c, codegen/kernel/reference.py)",
    c_prefix="dr",
    py_prefix="_S",
    state=(
        Field("q", "", "orientation, unit quaternion w, x, y, z turning body vectors into ENU", 4,
              initial=(1.0,), public="Q"),
        Field("v", "m/s", "velocity East, North, Up", 3, public="V"),
        Field("gyro_bias_lsb", "counts", "body-frame gyro bias", 3, public="GYRO_BIAS"),
    ),
    params=(
        Param("block", "samples", "b: samples per block median", Store("block", "samples"), kind="int", ge=1,
              error="ERR_BLOCK"),
        Param("window", "samples", "n: samples per window (the caller's buffer size)", Store("window", "samples"),
              kind="int", ge=1, multiple_of="block", error="ERR_WINDOW"),
        Param("accel_lsb_per_g", "counts per g", "accelerometer sensitivity",
              Store("accel_ms2_per_lsb", "m/s^2 per count", "recip", "GRAVITY_MS2"), gt=0),
        Param("gyro_lsb_per_dps", "counts per degree/s", "gyroscope sensitivity",
              Store("gyro_rads_per_lsb", "rad/s per count", "recip", "RAD_PER_DEG"), gt=0),
        Param("deadband_g", "g", "l: a block median with |a| below it becomes 0",
              Store("deadband_ms2", "m/s^2", "scale", "GRAVITY_MS2"), ge=0),
        Param("motion_threshold_g", "g", "calibration 'moved' when an accel axis' standard deviation exceeds this",
              Store("motion_limit_lsb2", "counts^2", "square", "accel_lsb_per_g"), gt=0),
    ),
    config_extra=(
        Field("axis_source", "", "body axis i <- sensor axis axis_source[i] (0..2), for accel and gyro alike", 3,
              ctype="int32_t"),
        Field("axis_sign", "", "... times axis_sign[i] (+1 or -1)", 3),
    ),
)

FUSED = Kernel(
    title="the fused method (dr_fused.c, codegen/kernel/fused.py)",
    c_prefix="dr_fused",
    py_prefix="_F",
    board_prefix="fused_",
    param_array=True,
    state=(
        Field("q", "", "orientation w, x, y, z: body -> kernel ENU", 4, ("qw", "qx", "qy", "qz"), initial=(1.0,),
              local="carry", group="the attitude and the motion statistics"),
        Field("gyro_bias_lsb", "counts", "gyro bias (body frame)", 3, ("bgx", "bgy", "bgz"), local="carry",
              public="FUSED_GYRO_BIAS"),
        Field("mean_f", "m/s^2", "mean |f| (motion statistics)", local="carry"),
        Field("var_f", "(m/s^2)^2", "variance of |f|", local="carry"),
        Field("vib_var", "(m/s^2)^2", "variance of |f| above the gait band (vibration_hz) over vibration_tau_s",
              local="carry"),
        Field("vib_tot", "(m/s^2)^2", "variance of |f| over vibration_tau_s (the vibration's share is of this)",
              local="carry"),
        Field("vib_lp", "m/s^2", "|f| low-passed at vibration_hz, and its high-passed part low-passed again", 2,
              ("vib_lp1", "vib_lp2"), local="carry"),
        Field("ws", "rad/s", "the body rate smoothed over stat_tau_s (an engine's shake averages out)", 3,
              ("wsx", "wsy", "wsz"), local="carry"),
        Field("speed", "m/s", "speed along the travel direction", local="carry",
              group="the speed along the travel direction"),
        Field("bias", "m/s^2", "along-track accelerometer bias", local="read"),
        Field("acc_lp", "m/s^2", "a vehicle's along-track acceleration smoothed over accel_tau_s", local="carry"),
        Field("zr_t", "s", "a vehicle: time since its speed was last known (a fix, a rest)", local="carry",
              group="a vehicle's zero-velocity update: its speed error's integrals since its speed was known"),
        Field("zr_p", "m s", "the integral of (time since then) x travel direction (true ENU) since then", 2,
              ("zr_pe", "zr_pn"), local="carry"),
        Field("zr_turn", "rad", "a vehicle: the integral of |rate about Up| since its speed was last known",
              local="carry"),
        Field("zr_v", "m/s", "a vehicle's speed integrated as speed is, without its floor at 0", local="carry"),
        Field("zr_c", "m", "the integral of (zr_v - speed) x travel direction (true ENU) since then", 2,
              ("zr_ce", "zr_cn"), local="carry"),
        Field("ux", "", "travel direction, kernel frame x (unit)", initial=(1.0,), local="carry",
              group="the travel direction"),
        Field("uy", "", "travel direction, kernel frame y", local="carry"),
        Field("rate_up", "rad/s", "the rate about Up smoothed over stat_tau_s", local="carry"),
        Field("held", "rad", "rotation about Up a walker's travel direction has not taken yet", local="carry"),
        Field("pe", "m", "true ENU position East accumulated since fused_init (the caller may reset it)",
              local="carry", group="the position, true ENU"),
        Field("pn", "m", "true ENU position North accumulated since fused_init", local="carry"),
        Field("flags", "", "the last sample's AT_REST | WALKING | TURNING (a whole number)",
              group="the platform and rest"),
        Field("rest_s", "s", "how long the device has looked at rest", local="carry"),
        Field("walk_s", "s", "how long the shaking has looked like steps", local="carry"),
        Field("walk_speed", "m/s", "learned walking speed", local="read"),
        Field("ah", "m/s^2", "the kernel-frame horizontal acceleration smoothed over stat_tau_s (rest: steady)", 2,
              ("ah_e", "ah_n"), local="carry"),
        Field("zt", "s", "at rest: time since the last rest update", local="carry"),
        Field("dvx", "m/s", "kernel-frame horizontal velocity change since the last fix, x", local="carry",
              group="what the samples gathered since the last fix (the fix and the tilt/offset filter read it)"),
        Field("dvy", "m/s", "kernel-frame horizontal velocity change since the last fix, y", local="carry"),
        Field("dpx", "m", "integral of dvx since the last fix", local="carry"),
        Field("dpy", "m", "integral of dvy since the last fix", local="carry"),
        Field("m", "s", "integral of R(q)'s horizontal rows r00, r01, r10, r11 since the last fix", 4,
              ("m00", "m01", "m10", "m11"), local="carry"),
        Field("m2", "s", "integral of R(q)'s horizontal rows' z column, r02 and r12, since the last fix", 2,
              ("m02", "m12"), local="carry"),
        Field("turn", "rad", "integral of |rate about Up| since the last fix", local="carry"),
        Field("fix_ae", "m", "smoothed position minus the last fix's, East (where an outage starts from)",
              public="FIX_AE", group="the position filter (the fix an outage starts from)"),
        Field("fix_an", "m", "smoothed position minus the last fix's, North"),
        Field("fix_ee", "m", "the receiver's position error estimated at the last fix, East"),
        Field("fix_en", "m", "the receiver's position error estimated at the last fix, North"),
        Field("fix_pxx", "m^2", "covariance of the position filter: position, position (East and North alike)"),
        Field("fix_pxe", "m^2", "covariance of the position filter: position, receiver error"),
        Field("fix_pee", "m^2", "covariance of the position filter: receiver error, receiver error"),
        Field("since_fix", "s", "time since the last GPS update", local="carry", group="the last fix"),
        Field("gps_ve", "m/s", "the last fix's velocity East (true ENU)"),
        Field("gps_vn", "m/s", "the last fix's velocity North (true ENU)"),
        Field("gps_speed", "m/s", "the last fix's speed (a vehicle's speed relaxes towards it)", local="read"),
        Field("gps_ok", "m/s", "> 0 if the last fix had a course: its speed - min_speed_ms"),
        Field("acc_e", "m/s^2", "GPS motion acceleration East, kernel frame (the tilt reference subtracts it)",
              local="read"),
        Field("acc_n", "m/s^2", "GPS motion acceleration North, kernel frame", local="read"),
        Field("steady", "(m/s^2)^2", "> 0 while that acceleration is steady: steady_accel_ms2^2 - its change^2"),
        Field("cos_t", "", "rotation kernel frame -> true ENU: cosine", initial=(1.0,), local="read",
              group="the kernel frame's heading: its alignment to true ENU"),
        Field("sin_t", "", "rotation kernel frame -> true ENU: sine", local="read"),
        Field("align_c", "(m/s)^2", "heading alignment sum, cosine part"),
        Field("align_s", "(m/s)^2", "heading alignment sum, sine part"),
        Field("bax", "m/s^2", "accelerometer offset of the body x axis (subtracted from every sample)", local="carry",
              group="the tilt/offset filter: the accelerometer's offsets and the covariance"),
        Field("bay", "m/s^2", "accelerometer offset of the body y axis", local="carry"),
        Field("baz", "m/s^2", "accelerometer offset of the body z axis (any mounting: no axis need be vertical)",
              local="carry"),
        Field("p", "", "the tilt/offset filter's covariance, upper triangle row by row (m/s^2 squared)", 10,
              ("p00", "p01", "p02", "p03", "p11", "p12", "p13", "p22", "p23", "p33")),
        Field("pz", "", "the tilt/offset filter's covariance, fifth column (the z offset): rows 0-4", 5,
              ("p04", "p14", "p24", "p34", "p44")),
        Field("kf_t", "s", "time since the tilt/offset filter's last prediction", local="carry"),
        Field("med_i", "", "the median option's ring: next slot (a whole number)", group="the median option's ring"),
        Field("med_n", "", "the median option's ring: slots filled (a whole number)"),
        Field("med", "m/s^2", "the median option's ring: the last along-track accelerations", FUSED_MEDIAN_MAX),
        Field("nh_t", "s", "a vehicle in an outage: time gathered towards the next lateral update", local="carry",
              group="a vehicle's lateral filter in an outage (nh_t first, nh_p last: the fallback zeroes the range)"),
        Field("nh_z", "m/s", "the integral of the lateral residual a_lat - speed x rate about Up over that time",
              local="carry"),
        Field("nh_r", "rad", "the integral of the rate about Up over that time", local="carry"),
        Field("nh_b", "m/s^2", "the lateral leak (horizontal specific force across the travel direction) estimated"),
        Field("nh_f", "m/s^2", "the accelerometer offsets folded into the tilt (their horizontal part when the outage "
              "started, kernel frame) estimated: a turn shows them", 2, ("nh_fx", "nh_fy"), local="read"),
        Field("nh_u0", "", "the travel direction u when the outage started (kernel frame)", 2, ("nh_u0x", "nh_u0y"),
              local="read"),
        Field("nh_i", "s", "the integral of u over the time gathered towards the next lateral update", 2,
              ("nh_ix", "nh_iy"), local="carry"),
        Field("nh_p", "", "the lateral filter's covariance, upper triangle row by row: speed error (m/s), lateral leak, "
              "folded offsets x, y (m/s^2); all 0 until the outage's first sample", 10,
              ("nh_pss", "nh_psb", "nh_psx", "nh_psy", "nh_pbb", "nh_pbx", "nh_pby", "nh_pxx", "nh_pxy", "nh_pyy")),
        Field("cov_repairs", "", "how often a filter's covariance went wrong (a negative variance, a value not finite, "
              "an update's innovation variance not positive) and was reset to its prior instead of used (a whole "
              "number)", public="COV_REPAIRS", group="the filters' health"),
        Field("sb_p", "", "the speed/bias filter's covariance at the last fix (or rest), upper triangle: speed (m/s), "
              "along-track bias (m/s^2); the bias's 0 until its first fix, the speed's large after a calibration that "
              "moved", 3, ("sb_pss", "sb_psb", "sb_pbb"),
              group="a vehicle's speed and along-track bias filter, and the speed it keeps"),
        Field("sk_t", "s", "time since the speed was last known (a fix, a rest, calibration)", local="carry"),
        Field("keep_v", "m/s", "the speed a vehicle is taken to keep (the last fix's); < 0 before a fix and after a "
              "rest: none", initial=(-1.0,), local="carry"),
        Field("sb_lost", "m/s", "the along-track acceleration the deadband kept out of a vehicle's integrated speed "
              "since the speed was last known, integrated: its square is noise of the speed at the next fix, not a "
              "bias", local="carry"),
        Field("cal_moved", "", "1 from a calibration that moved until the next rest (the gyro bias took the motion's "
              "mean rate for a bias: the tilt drifts), else 0", public="CAL_MOVED"),
    ),
    # what fused_keep copies out and fused_restore takes up after a reset: the attitude, the gyro's bias, the
    # accelerometer's offsets with their block of the tilt/offset filter's covariance, the along-track bias with its
    # variance, the walking speed (body-frame or the device's own; nothing of the kernel frame's heading)
    kept=("qw", "qx", "qy", "qz", "bgx", "bgy", "bgz", "bax", "bay", "baz", "p22", "p23", "p24", "p33", "p34", "p44",
          "bias", "sb_pbb", "walk_speed"),
    params=(
        Param("tilt_tau_s", "s", "tilt correction time constant while GPS fixes arrive", Store("kp", "1/s", "recip"),
              100.0, gt=0),
        Param("accel_reject_g", "g", "no tilt correction while ||f| - g| exceeds this",
              Store("reject_ms2", "m/s^2", "scale", "GRAVITY_MS2"), 0.1, gt=0),
        Param("tilt_tau_dark_s", "s", "tilt correction time constant without GPS (0: none)",
              Store("kp_dark", "1/s", "rate"), 0.0, ge=0),
        Param("steady_accel_ms2", "m/s^2",
              "tilt corrected only while the GPS acceleration changes less between fixes",
              Store("steady_ms2", "m/s^2"), 0.3, gt=0),
        Param("speed_tau_s", "s", "a vehicle's speed relaxes towards the last GPS speed (0: never)",
              Store("inv_speed_tau", "1/s", "rate"), 0.0, ge=0),
        Param("gps_timeout_s", "s", "GPS counts as lost this long after its last fix", Store("gps_timeout_s", "s"),
              2.0, gt=0),
        Param("stat_tau_s", "s", "time constant of the motion statistics", Store("inv_stat_tau", "1/s", "recip"),
              0.5, gt=0),
        Param("rest_accel_g", "g", "|f| standard deviation below which the device may be at rest",
              Store("rest_var", "(m/s^2)^2", "square", "GRAVITY_MS2"), 0.01, gt=0),
        Param("rest_gyro_dps", "degree/s", "rate below which the device may be at rest",
              Store("rest_w2", "(rad/s)^2", "square", "RAD_PER_DEG"), 0.5, gt=0),
        Param("rest_time_s", "s", "both below their limits this long means at rest", Store("rest_time_s", "s"),
              0.4, ge=0),
        Param("bias_tau_s", "s", "gyro bias re-estimation time constant at rest (0: off)",
              Store("inv_bias_tau", "1/s", "rate"), 30.0, ge=0),
        Param("walk_accel_g", "g", "|f| standard deviation above which a walker carries the device",
              Store("walk_var", "(m/s^2)^2", "square", "GRAVITY_MS2"), 0.03, gt=0),
        Param("min_speed_ms", "m/s", "GPS speeds below this carry no course", Store("min_speed_ms", "m/s"), 0.5, ge=0),
        Param("heading_gain", "per fix", "pull of the travel direction towards the GPS course",
              Store("heading_gain", "per fix"), 0.3, ge=0, le=1),
        Param("align_forget", "per fix", "forgetting factor of the heading alignment", Store("align_forget", "per fix"),
              0.98, ge=0, le=1),
        Param("speed_gain", "per fix", "pull of the speed towards the GPS speed", Store("speed_gain", "per fix"), 0.5,
              ge=0, le=1),
        Param("walk_speed_gain", "per fix", "pull of the walking speed towards the GPS speed",
              Store("walk_speed_gain", "per fix"), 0.2, ge=0, le=1),
        Param("kf_bias_init_g", "g",
              "initial sigma of the horizontal accelerometer offsets (0: no tilt/offset filter)",
              Store("kf_bias_var", "(m/s^2)^2", "square", "GRAVITY_MS2"), 0.05, ge=0),
        Param("kf_bias_noise", "m/s^2/sqrt(s)", "random walk of those offsets",
              Store("kf_bias_q", "(m/s^2)^2/s", "square"), 0.001, ge=0),
        Param("kf_tilt_noise", "m/s^2/sqrt(s)", "random walk of the gravity leak (tilt error times g)",
              Store("kf_tilt_q", "(m/s^2)^2/s", "square"), 0.002, ge=0),
        Param("kf_turn_noise", "m/s^2 per rad", "gravity leak a turn may add (gyro scale and cross-axis errors)",
              Store("kf_turn_q", "(m/s^2/rad)^2", "square"), 0.1, ge=0),
        Param("kf_vel_sigma_ms", "m/s", "GPS Doppler velocity error per axis, with unmodelled motion",
              Store("kf_vel_r", "(m/s)^2", "square", times=2.0), 0.15, gt=0),
        Param("kf_align_min", "(m/s)^2", "heading alignment sums needed before the filter updates (a fix then weighs "
              "by the alignment's angle error too: a straight road's weak alignment no longer keeps it off)",
              Store("kf_align_min", "(m/s)^2"), 1.0, ge=0),
        Param("median", "", "a vehicle's along-track acceleration is the median of the last b (block) samples: the "
              f"seed's block median, sliding (b <= {FUSED_MEDIAN_MAX})", Store("median", "1: on"), False, kind="bool"),
        Param("pos_sigma_m", "m",
              "the receiver's position error per axis, for smoothing the fix an outage starts from (0: raw fixes)",
              Store("pos_var", "m^2", "square"), 2.1, ge=0),
        Param("pos_tau_s", "s", "correlation time of that error", Store("inv_pos_tau", "1/s", "recip"), 60.0, gt=0),
        Param("pos_step_sigma_ms", "m/s",
              "error of the step between fixes (Doppler trapezoid + IMU), per second",
              Store("pos_step_q", "(m/s)^2", "square"), 0.1, gt=0),
        Param("turn_hold_tau_s", "s", "a walker's slow rotations about Up (the hand swinging about the course) "
              "reach the travel direction over this; turns at once (0: everything at once)",
              Store("hold_rate", "1/s", "rate"), 10.0, ge=0),
        Param("turn_start_dps", "degree/s", "a walker's turn starts when the smoothed rate about Up exceeds this",
              Store("turn_start", "rad/s", "scale", "RAD_PER_DEG"), 12.0, gt=0),
        Param("turn_end_dps", "degree/s", "and ends when it falls below this (at most fused_turn_start_dps)",
              Store("turn_end", "rad/s", "scale", "RAD_PER_DEG"), 7.0, ge=0, at_most="turn_start_dps",
              at_most_why="a turn that ends at {value:g} {unit} cannot start at the lower {limit:g} {unit}"),
        Param("platform", "", "what carries the device: a pedestrian (any shaking is steps), a vehicle (never steps) "
              "or auto (steps only while the shaking stays below vibration_hz)", Store("platform", "choice"), "auto",
              kind="choice", choices=("pedestrian", "vehicle", "auto")),
        Param("vibration_hz", "Hz", "the gait band's upper edge: |f| varying faster is a vehicle's road or engine",
              Store("vib_rate", "rad/s", "scale", "RAD_PER_CYCLE"), 8.0, gt=0),
        Param("vibration_ratio", "", "auto: shaking with more than this share of its variance above vibration_hz is a "
              "vehicle's, not steps", Store("vib_ratio", ""), 0.04, ge=0, le=1),
        Param("vibration_tau_s", "s", "time constant of the two variances that share is of",
              Store("inv_vib_tau", "1/s", "recip"), 2.0, gt=0),
        Param("walk_time_s", "s", "steps this long start a walk (a vehicle's odd second of calm shaking does not)",
              Store("walk_time_s", "s"), 1.0, ge=0),
        Param("rest_speed_ms", "m/s", "a quiet vehicle comes to rest with any steady horizontal specific force (its "
              "tilt error in an outage) while its speed is below this, or after it shook",
              Store("rest_speed_ms", "m/s"), 1.0, ge=0),
        Param("rest_gate", "", "and only if the tilt/offset filter can take that force for its own error: its "
              "normalised square below this (chi-square, 2 degrees of freedom; 13.8: 99.9 %). A car pulling away "
              "smoothly from a stand is as quiet and steady as one that stands (0: any force)",
              Store("rest_gate", ""), 13.8, ge=0),
        Param("rest_update_s", "s", "at rest, every this long (after the first), the gyro bias and the tilt/offset "
              "filter take the smoothed rate and horizontal specific force as their errors",
              Store("rest_update_s", "s"), 1.0, gt=0),
        Param("kf_rest_sigma_ms2", "m/s^2", "error of that smoothed horizontal specific force (0: no filter update at "
              "rest)", Store("kf_rest_r", "(m/s^2)^2", "square"), 0.03, ge=0),
        Param("zupt_turn_weight", "1/rad", "a vehicle's zero-velocity update takes its speed error as grown at a rate "
              "1 + this x the turn since its speed was last known (turns make the tilt errors)",
              Store("zupt_turn_weight", "1/rad"), 3.0, ge=0),
        Param("accel_tau_s", "s", "a vehicle's along-track acceleration passes the deadband while its average over "
              "this does (the road's shaking averages out; 0: each sample on its own)",
              Store("inv_accel_tau", "1/s", "rate"), 0.5, ge=0),
        Param("deadband_ramp_s", "s", "a vehicle's deadband grows from 0 at a fix to the board's l over this: the "
              "gravity leak it keeps out grows with the time since a fix corrected the tilt, while a car's gentle "
              "accelerations in traffic are there from the first second (0: l at once)",
              Store("inv_deadband_ramp", "1/s", "rate"), 10.0, ge=0),
        Param("nhc_sigma_ms2", "m/s^2", "a vehicle in an outage: error of the lateral residual a_lat - speed x rate "
              "about Up averaged over 1 s, which sees the speed error in turns (0: no lateral update)",
              Store("nhc_var", "(m/s^2)^2", "square"), 0.15, ge=0),
        Param("nhc_period_s", "s", "the lateral residual is averaged over this between updates",
              Store("nhc_period_s", "s"), 0.5, gt=0),
        Param("nhc_speed_noise", "m/s/sqrt(s)", "random walk of a vehicle's speed error in an outage",
              Store("nhc_speed_q", "(m/s)^2/s", "square"), 0.3, ge=0),
        Param("nhc_leak_sigma_ms2", "m/s^2", "the lateral leak's sigma when the outage starts (or after a rest)",
              Store("nhc_leak_var", "(m/s^2)^2", "square"), 0.1, ge=0),
        Param("nhc_min_rate", "rad/s", "the speed error is seen only while the rate about Up averaged over "
              "nhc_period_s exceeds this (a turn, not a wobble)", Store("nhc_min_rate", "rad/s"), 0.1, ge=0),
        Param("nhc_position", "", "the share of the position error a lateral update's speed correction implies (as "
              "the zero-velocity update takes it) that is taken back", Store("nhc_position", ""), 1.0, ge=0, le=1),
        Param("nhc_leak_turn", "m/s^2 per rad", "lateral leak a turn may add (offsets folded into the tilt)",
              Store("nhc_leak_turn", "m/s^2 per rad"), 0.3, ge=0),
        Param("nhc_fold_scale", "", "a vehicle in an outage: the accelerometer offsets the tilt/offset filter has not told "
              "apart from the tilt (its covariance, times this) are estimated too; a turn turns them against the tilt, "
              "which shows them along and across the track (0: not estimated)", Store("nhc_fold_scale", ""), 1.0, ge=0),
        Param("pedestrian_max_ms", "m/s", "auto: a fix faster than this (people walk at up to ~3 m/s and run at up to "
              "~6) makes the device a vehicle, which no steps turn into a pedestrian until it has rested; nor do steps "
              "while a vehicle's own speed is above it", Store("pedestrian_max_ms", "m/s"), 6.0, gt=0),
        Param("still_accel_g", "g", "|f| standard deviation up to which a pedestrian may still be at rest if the rest "
              "is more than quiet: a hand (steady horizontal force, averaged rate below fused_rest_gyro_dps)",
              Store("still_var", "(m/s^2)^2", "square", "GRAVITY_MS2"), 0.04, ge=0),
        Param("idle_accel_g", "g", "and a vehicle, if its shaking is above fused_vibration_hz (an idling engine) and "
              "its speed below fused_rest_speed_ms (a real highway drive shook less than 30 mg with its averaged rate "
              "below fused_rest_gyro_dps in 6.6 % of its samples, 40 mg in 40 %)",
              Store("idle_var", "(m/s^2)^2", "square", "GRAVITY_MS2"), 0.03, ge=0),
        Param("stand_tau_s", "s", "a pedestrian whose steps stopped without a rest: the speed decays to 0 with this "
              "time constant, never integrated (0: held)", Store("inv_stand_tau", "1/s", "rate"), 1.0, ge=0),
        Param("speed_noise", "m/s/sqrt(s)", "a vehicle's integrated speed: random walk of its error beyond the "
              "along-track bias's (what the deadband keeps out)", Store("speed_q", "(m/s)^2/s", "square"), 0.1, ge=0),
        Param("speed_bias_noise", "m/s^2/sqrt(s)", "random walk of the along-track bias after a calibration that moved "
              "and before a rest (the gyro bias is off by the motion's mean rate during calibration, so the tilt "
              "drifts; otherwise fused_kf_tilt_noise)", Store("speed_bias_q", "(m/s^2)^2/s", "square"), 0.05, ge=0),
        Param("keep_speed_noise", "m/s/sqrt(s)", "a vehicle keeps its speed: random walk of its true speed away from "
              "the last fix's, the prior its integrated speed is weighed against by their variances (0: no prior)",
              Store("keep_q", "(m/s)^2/s", "square"), 1.0, ge=0),
        Param("max_accel_ms2", "m/s^2", "a vehicle's speed stays within [0, the speed last known + this x the time "
              "since]", Store("max_accel_ms2", "m/s^2"), 4.0, gt=0),
        Param("carried_ms", "m/s", "auto: a fix faster than this while no steps are seen makes the device a vehicle "
              "until it rests, as a fix faster than fused_pedestrian_max_ms does (a pedestrian who moves that fast "
              "steps; slow traffic does not)", Store("carried_ms", "m/s"), 2.5, gt=0),
        Param("vehicle_walk_time_s", "s", "auto: steps this long make a pedestrian of a device that drove (a fix "
              "faster than fused_pedestrian_max_ms, or than fused_carried_ms without steps, since its last walk; a "
              "rest does not end it): a car creeping on in a queue shakes in the gait band for seconds at a time",
              Store("vehicle_walk_time_s", "s"), 10.0, ge=0),
    ),
    flags=(
        Flag("AT_REST", 1, "the last sample was at rest"),
        Flag("WALKING", 2, "the last sample looked like a walker's"),
        Flag("TURNING", 4, "the walker was turning"),
        Flag("VEHICLE", 8, "the last shaking was a vehicle's (above vibration_hz), or the platform is a vehicle"),
        Flag("SHAKEN", 16, "a vehicle shaken (beyond walk_accel_g) since its last rest: if it goes quiet, it stopped"),
        Flag("FAST", 32, "a fix since the last rest was faster than pedestrian_max_ms: a vehicle, until it rests"),
        Flag("WALKED", 64, "a pedestrian: walked, and no fast fix since (a walker's stops keep it)"),
        Flag("DROVE", 128, "a fix since the last walk set FAST: the device drove; its rests keep this, and its steps "
             "must last vehicle_walk_time_s to make a pedestrian of it"),
    ),
)



# The error-state filter (native_ext/dr_eskf.h, codegen/kernel/eskf.py). Its structs are written by hand in dr_eskf.h
# (the filter's C is not rendered); this is what the rest agrees with: dr_layout.h renders the lengths, the offsets
# and, from them, a compile-time check of every field of dr_eskf.h's structs (DR_ESKF_*_FIELDS), so a header that
# drifts from here does not compile; codegen/kernel/hosteskf.py declares its cffi structs from here; dr_native's
# eskf buffer is dr_eskf_state | dr_eskf_config | dr_config. Every parameter is a float copied as it is given
# (EskfConfig's names, units and defaults); the two cadences keep the defaults the filter was tested at.
ESKF = Kernel(
    title="the error-state filter (dr_eskf.c, codegen/kernel/eskf.py)",
    c_prefix="dr_eskf",
    py_prefix="_E",
    board_prefix="eskf_",
    state=(
        Field("pos", "m", "position E N U, the run's ENU frame", 3, public="ESKF_POS", group="the nominal state"),
        Field("vel", "m/s", "velocity E N U", 3, public="ESKF_VEL"),
        Field("q", "", "attitude w x y z, body -> ENU", 4, initial=(1.0,), public="ESKF_Q"),
        Field("bg", "rad/s", "gyro bias, body", 3),
        Field("ba", "m/s^2", "accelerometer bias, body", 3),
        Field("sg", "1", "the gyro's turn-rate error per rad/s about Up, body", 3),
        Field("ge", "m", "the receiver's position error E N U", 3),
        Field("mount", "", "body -> vehicle (x forward, y left, z up)", 9, shape=(3, 3), initial=(1.0, 0, 0, 0, 1.0,
              0, 0, 0, 1.0)),
        Field("acc_a", "s", "sum of R dt since the last propagation", 9, shape=(3, 3),
              group="the sums since the last covariance propagation"),
        Field("acc_b", "rad", "sum of R turn dt", 9, shape=(3, 3)),
        Field("acc_dv", "m/s", "sum of R f dt", 3),
        Field("acc_t", "s", "the interval"),
        Field("sat_dv", "m/s", "what clipped samples may have lost in it"),
        Field("since_nhc", "s", "since the last pseudo-measurement", group="rest and motion"),
        Field("mean_f", "m/s^2", "|f| smoothed"),
        Field("var_f", "(m/s^2)^2", "its variance"),
        Field("ws", "rad/s", "the rate smoothed", 3),
        Field("ah", "m/s^2", "the horizontal specific force smoothed", 2),
        Field("rest_s", "s", "at rest so far"),
        Field("rate2", "(rad/s)^2", "the last sample's rate squared"),
        Field("gps_speed", "m/s", "the last fix's speed (0 in an outage: rest may be detected)",
              public="ESKF_GPS_SPEED", group="the fixes and the yaw alignment"),
        Field("t_fix", "s", "the last fix's time"),
        Field("al_du", "m/s", "the wander frame's velocity change since the last fix", 2),
        Field("al_u", "1", "the body's heading in the wander frame since the calibration, E + i N", 2,
              initial=(1.0, 0.0)),
        Field("al_s", "s", "its integral since the last fix", 2),
        Field("al_sums", "", "the yaw fit's sums (DR_ESKF_AL_*)", 10),
        Field("al_prev", "m/s", "the previous fix's velocity", 2),
        Field("al_have_prev", "1", "1 once a fix was seen"),
        Field("aligned", "1", "1 once the filter runs", public="ESKF_ALIGNED"),
        Field("gyro_moving", "1", "1 if calibration saw motion"),
        Field("cov_repairs", "", "covariances that went wrong and were reset", public="ESKF_COV_REPAIRS"),
        Field("p", "", "the error state's covariance, symmetric", 23 * 23, shape=(23, 23), group="the covariance"),
    ),
    params=(
        Param("cov_dt_s", "s", "between covariance propagations", Store("cov_dt_s", "s"), 0.2, gt=0, board=False),
        Param("nhc_dt_s", "s", "between pseudo-measurements", Store("nhc_dt_s", "s"), 0.4, gt=0, board=False),
        Param("accel_noise", "m/s^2/sqrt(Hz)", "white specific-force noise, the vehicle's shaking included",
              Store("accel_noise", "m/s^2/sqrt(Hz)"), 0.05, gt=0),
        Param("gyro_noise", "rad/s/sqrt(Hz)", "white gyro noise", Store("gyro_noise", "rad/s/sqrt(Hz)"), 0.002, gt=0),
        Param("accel_bias_walk", "m/s^2/sqrt(s)", "accelerometer bias random walk",
              Store("accel_bias_walk", "m/s^2/sqrt(s)"), 2e-4, ge=0),
        Param("gyro_bias_walk", "rad/s/sqrt(s)", "gyro bias random walk", Store("gyro_bias_walk", "rad/s/sqrt(s)"),
              2e-5, ge=0),
        Param("mount_walk", "rad/sqrt(s)", "the mounting's random walk", Store("mount_walk", "rad/sqrt(s)"), 2e-4,
              ge=0),
        Param("turn_scale_walk", "1/sqrt(s)", "the turn-rate error's random walk", Store("turn_scale_walk",
              "1/sqrt(s)"), 1e-5, ge=0),
        Param("gps_pos_sigma", "m", "the receiver's position error per horizontal axis (Gauss-Markov)",
              Store("gps_pos_sigma", "m"), 2.12, gt=0),
        Param("gps_up_sigma", "m", "and up", Store("gps_up_sigma", "m"), 3.2, gt=0),
        Param("gps_tau_s", "s", "its correlation time", Store("gps_tau_s", "s"), 60.0, gt=0),
        Param("gps_white_sigma", "m", "the position error that is not correlated, per axis",
              Store("gps_white_sigma", "m"), 0.3, gt=0),
        Param("gps_vel_sigma", "m/s", "the Doppler velocity's error per horizontal axis", Store("gps_vel_sigma",
              "m/s"), 0.15, gt=0),
        Param("gps_slow_sigma", "m/s", "the velocity's error when the receiver reports 0 (below its course's speed)",
              Store("gps_slow_sigma", "m/s"), 0.4, gt=0),
        Param("nhc_sigma", "m/s", "the vehicle's lateral and vertical velocity (lever arm, slip, roll)",
              Store("nhc_sigma", "m/s"), 0.6, gt=0),
        Param("saturation_excess_ms2", "m/s^2", "what a clipped sample (the range's end) may have lost",
              Store("saturation_excess_ms2", "m/s^2"), 20.0, ge=0),
        Param("nhc_lever_m", "m", "the device's distance from the vehicle's axles", Store("nhc_lever_m", "m"), 1.0,
              ge=0),
        Param("nhc_gate", "sigmas", "a lateral or vertical velocity beyond this is no sliding", Store("nhc_gate",
              "sigmas"), 3.0, gt=0),
        Param("nhc_min_speed", "m/s", "the constraint's mounting terms need this speed", Store("nhc_min_speed",
              "m/s"), 1.0, ge=0),
        Param("zupt_sigma", "m/s", "zero velocity's error", Store("zupt_sigma", "m/s"), 0.02, gt=0),
        Param("zupt_gate", "1", "the velocity's normalised square below which it may be 0 (chi-square, 3 dof)",
              Store("zupt_gate", "1"), 16.3, gt=0),
        Param("zaru_sigma", "rad/s", "the smoothed rate at rest against the bias", Store("zaru_sigma", "rad/s"),
              0.002, gt=0),
        Param("rest_accel_g", "g", "|f| standard deviation below which the vehicle may be at rest (an idling engine)",
              Store("rest_accel_g", "g"), 0.02, ge=0),
        Param("rest_gyro_dps", "degree/s", "smoothed rate below which it may be at rest", Store("rest_gyro_dps",
              "degree/s"), 1.0, ge=0),
        Param("rest_time_s", "s", "both this long", Store("rest_time_s", "s"), 0.5, ge=0),
        Param("rest_speed_ms", "m/s", "and the last fix's speed below this (while fixes arrive)",
              Store("rest_speed_ms", "m/s"), 1.5, ge=0),
        Param("rest_horizontal_ms2", "m/s^2", "and the smoothed horizontal specific force below this",
              Store("rest_horizontal_ms2", "m/s^2"), 0.3, ge=0),
        Param("stat_tau_s", "s", "the shaking's and the rate's smoothing", Store("stat_tau_s", "s"), 0.5, gt=0),
        Param("align_fixes", "fix intervals", "the yaw fit needs at least this many (and 3)",
              Store("align_fixes", "fix intervals"), 5.0, ge=0),
        Param("align_yaw_sigma_deg", "degree", "the fitted yaw's 1-sigma below which the filter starts (at most the "
              "prior's, init_yaw_sigma_deg)", Store("align_yaw_sigma_deg", "deg"), 10.0, gt=0),
        Param("align_scale", "1", "the fit's GPS velocity change over the IMU's within [1 / this, this]",
              Store("align_scale", "1"), 1.25, ge=1),
        Param("align_speed_ms", "m/s", "the filter starts while moving at least this fast", Store("align_speed_ms",
              "m/s"), 2.0, ge=0),
        Param("init_yaw_sigma_deg", "degree", "the yaw's sigma at the start", Store("init_yaw_sigma_deg", "deg"),
              10.0, gt=0),
        Param("init_tilt_sigma_deg", "degree", "the tilt's, after a calibration at rest",
              Store("init_tilt_sigma_deg", "deg"), 0.3, gt=0),
        Param("init_tilt_moving_deg", "degree", "after a calibration in motion", Store("init_tilt_moving_deg", "deg"),
              2.0, gt=0),
        Param("init_gyro_bias_dps", "degree/s", "the gyro bias's, after a calibration at rest",
              Store("init_gyro_bias_dps", "deg/s"), 0.1, gt=0),
        Param("init_gyro_bias_moving_dps", "degree/s", "after a calibration in motion",
              Store("init_gyro_bias_moving_dps", "deg/s"), 0.5, gt=0),
        Param("init_accel_bias_ms2", "m/s^2", "the accelerometer bias's", Store("init_accel_bias_ms2", "m/s^2"), 0.3,
              gt=0),
        Param("init_mount_sigma_deg", "degree", "the mounting's", Store("init_mount_sigma_deg", "deg"), 5.0, gt=0),
        Param("init_turn_scale", "1", "the turn-rate error's (the MPU-6050's sensitivity and cross-axis errors)",
              Store("init_turn_scale", "1"), 0.03, gt=0),
    ),
)


@dataclass(frozen=True)
class Layout:
    """What the templates render from: both kernels, and the buffers dr_native and dr_fallback hand the app
    (the seed's: dr_state | dr_config | scratch; the fused one's: dr_fused_state | dr_fused_config | dr_config)."""

    seed: Kernel
    fused: Kernel
    eskf: Kernel
    codes: tuple[Code, ...] = RETURN_CODES
    out_floats: int = OUT_FLOATS
    median_max: int = FUSED_MEDIAN_MAX
    constants: dict = field(default_factory=lambda: dict(CONSTANTS))
    filters: tuple[str, ...] = COVARIANCE_FILTERS
    filter_steps: tuple[str, ...] = FILTER_STEPS

    @property
    def kernels(self) -> tuple[Kernel, ...]:
        return (self.seed, self.fused)

    @property
    def seed_header_floats(self) -> int:
        """Floats of the seed buffer before its scratch (state_len(block) = this + 3 * block)."""
        return self.seed.state_floats + self.seed.config_floats

    @property
    def fused_config_at(self) -> int:
        return self.fused.state_floats

    @property
    def fused_kernel_config_at(self) -> int:
        return self.fused.state_floats + self.fused.config_floats

    @property
    def fused_buffer_floats(self) -> int:
        return self.fused_kernel_config_at + self.seed.config_floats

    @property
    def eskf_config_at(self) -> int:
        return self.eskf.state_floats

    @property
    def eskf_kernel_config_at(self) -> int:
        return self.eskf.state_floats + self.eskf.config_floats

    @property
    def eskf_buffer_floats(self) -> int:
        """The eskf buffer dr_native hands the app: dr_eskf_state | dr_eskf_config | dr_config."""
        return self.eskf_kernel_config_at + self.seed.config_floats

    def fused_config_in_buffer(self) -> dict[str, int]:
        """dr_fused_config field -> its offset in the fused buffer."""
        return {name: self.fused_config_at + at for name, at in self.fused.config_offsets.items()}


def check(kernel: Kernel) -> None:
    """Raise ValueError where the declaration contradicts itself (a deadreckon bug, caught on import)."""
    names = [f.name for f in kernel.state]
    stored = [f.name for f in kernel.config]
    params = kernel.param_names
    elements = kernel.element_names()
    for what, seen in (("state field", names), ("configuration field", stored), ("parameter", params),
                       ("state value", elements)):
        twice = sorted({n for n in seen if seen.count(n) > 1})
        if twice:
            raise ValueError(f"{kernel.c_prefix}: {what} declared twice: {', '.join(twice)}")
    for f in kernel.state + kernel.config:
        if f.ctype not in ("float", "int32_t") or f.length < 1 or len(f.initial) > f.length:
            raise ValueError(f"{kernel.c_prefix}: field {f.name}: ctype, length or initial values wrong")
        if f.shape and math.prod(f.shape) != f.length:
            raise ValueError(f"{kernel.c_prefix}: field {f.name}: shape {f.shape} is not {f.length} values")
        if f.elements and len(f.elements) != f.length:
            raise ValueError(f"{kernel.c_prefix}: field {f.name} names {len(f.elements)} of {f.length} elements")
    for p in kernel.params:
        s = p.store
        if s.form not in ("copy", "scale", "recip", "rate", "square"):
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: unknown form {s.form!r}")
        if s.factor is not None and s.factor not in CONSTANTS and s.factor not in params:
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: factor {s.factor!r} is neither a constant "
                             "nor a parameter")
        if s.form == "recip" and not (p.gt is not None and p.gt >= 0):
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: a reciprocal needs gt >= 0")
        if s.form == "rate" and s.factor is not None:
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: a rate takes no factor")
        for other in (p.at_most, p.multiple_of):
            if other is not None and other not in params[:params.index(p.name)]:
                raise ValueError(f"{kernel.c_prefix}: parameter {p.name} refers to {other!r}, not an earlier "
                                 "parameter")
        if p.kind not in ("float", "int", "bool", "choice") or (
                p.kind in ("bool", "choice") and (p.gt, p.ge, p.le, p.at_most, p.multiple_of) != (None,) * 5):
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: kind {p.kind!r} or its limits wrong")
        if (p.kind == "choice") != bool(p.choices) or (p.kind == "choice" and p.default not in p.choices):
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: a choice needs choices and one as default")
        if p.error not in {c.name for c in RETURN_CODES}:
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name}: unknown return code {p.error!r}")
        if (kernel.board_prefix or not p.board) and p.default is None:
            raise ValueError(f"{kernel.c_prefix}: parameter {p.name} has a board key but no default")
    taken = {n.upper() for n in names + list(params) + [fl.name for fl in kernel.flags]}
    clash = sorted(name for _, _, name in kernel.named_elements() if name.upper() in taken)
    if clash:
        raise ValueError(f"{kernel.c_prefix}: element names that are also a field, parameter or flag (their index "
                         f"constants would clash): {', '.join(clash)}")
    for f in kernel.state:
        if f.local not in ("", "read", "carry") or (f.local and f.length > 1 and not f.elements):
            raise ValueError(f"{kernel.c_prefix}: field {f.name}: local is '', 'read' or 'carry' (an array's elements "
                             "named)")
    unknown = [name for name in kernel.kept if name not in kernel.element_offsets()]
    if unknown or len(set(kernel.kept)) != len(kernel.kept):
        raise ValueError(f"{kernel.c_prefix}: kept names a value twice or one the state lacks: {', '.join(unknown)}")
    if any(f.ctype != "float" for f in kernel.state):
        raise ValueError(f"{kernel.c_prefix}: state fields are floats (the reference's flat view)")


LAYOUT = Layout(SEED, FUSED, ESKF)
for _kernel in LAYOUT.kernels + (ESKF,):
    check(_kernel)
