"""The C kernel on the host: the board's rendered sources compiled with cffi (API mode), cached by source hash.

    kernel = load_kernel(loaded_board)          # or load_kernel() for the default board
    run = kernel.session(block=16)              # a dr_config + dr_state + scratch, caller-owned like on the device
    moved = run.calibrate(samples_at_rest)      # (M, 6) int16 counts
    disp, vel, medians = run.process(samples, dt_us)

The very files `deadreckon generate` writes into OUT/native/ are compiled (codegen.generate.render_tree), first
alone with `-std=c99 -Wall -Wextra -Werror -pedantic` (a compiler error becomes a UserError naming the rendered file
and line), then linked into a cffi extension. The build lives in $DEADRECKON_CACHE (default ~/.cache/deadreckon)
under the hash of the sources, the flags and the Python version, so a second load is an import.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

from codegen.errors import Location, UserError

KERNEL_SOURCES = ("dr_kernel.c", "dr_median.c", "dr_geo.c")
KERNEL_HEADERS = ("dr_kernel.h", "dr_layout.h", "dr_median.h", "dr_geo.h", "dr_math.h", "dr_board.h")
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-fPIC")

# The structs' fields the wrappers touch; `...;` lets cffi take the layout from the rendered dr_layout.h, so a field
# added to the declaration (codegen/kernel/layout.py) needs no change here.
CONFIG_CDEF = """
typedef struct {
    int32_t block;
    int32_t window;
    int32_t axis_source[3];
    float axis_sign[3];
    float accel_ms2_per_lsb;
    float gyro_rads_per_lsb;
    float deadband_ms2;
    float motion_limit_lsb2;
    ...;
} dr_config;
void dr_config_init(dr_config *cfg);
"""

CDEF = CONFIG_CDEF + """
typedef struct {
    float q[4];
    float v[3];
    float gyro_bias_lsb[3];
    ...;
} dr_state;
int dr_config_set(dr_config *cfg, int32_t block, int32_t window, float accel_lsb_per_g, float gyro_lsb_per_dps,
                  float deadband_g, float motion_threshold_g);
void dr_state_init(dr_state *st);
int dr_calibrate(const dr_config *cfg, dr_state *st, const int16_t *samples, int32_t count);
int dr_process(const dr_config *cfg, dr_state *st, float *scratch, const int16_t *samples, const int32_t *dt_us,
               int32_t count, float out[6], float *medians);
void dr_set_velocity(dr_state *st, float ve, float vn, float vu);
void dr_rotate_heading(dr_state *st, float cos_a, float sin_a);
int32_t dr_block_median(float *x, int32_t count, int32_t block, float *out);
float dr_median(float *x, int32_t count);
void dr_offset_latlon(int32_t lat_e7, int32_t lon_e7, float east_m, float north_m, int32_t *lat_out,
                      int32_t *lon_out);
float dr_sin_half_pi(float x);
"""

ERRORS = {
    -1: "block size must be at least 1",
    -2: "the window must be a positive multiple of the block size",
    -3: "the sample count must be a positive multiple of the block size",
    -4: "ranges and the motion threshold must be positive and the deadband not negative",
}

_DIAGNOSTIC = re.compile(r"^(?P<file>[^:\n]+):(?P<line>\d+):(?P<col>\d+): (?:fatal )?error: (?P<msg>.*)$", re.M)


def cache_dir() -> Path:
    """Where built kernels live: $DEADRECKON_CACHE, else ~/.cache/deadreckon."""
    root = os.environ.get("DEADRECKON_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "deadreckon"


def kernel_sources(loaded=None, extra: tuple[str, ...] = ()) -> dict[str, bytes]:
    """The kernel's C files (name -> content) exactly as `deadreckon generate` renders them for the board, plus
    the `extra` files named (the fused kernel's)."""
    from codegen.board.loader import load_board
    from codegen.generate import render_tree

    tree = render_tree(loaded if loaded is not None else load_board())
    wanted = set(KERNEL_SOURCES) | set(KERNEL_HEADERS) | set(extra)
    files = {name[len("native/"):]: f.content for name, f in tree.items() if name[len("native/"):] in wanted}
    missing = wanted - set(files)
    if missing:
        raise UserError(f"the generated tree lacks kernel file(s) {', '.join(sorted(missing))} (a deadreckon bug)")
    return files


def _compiler() -> list[str]:
    return (os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc").split()


def _compile_objects(folder: Path, sources: tuple[str, ...], defines: tuple[str, ...] = ()) -> list[Path]:
    """Compile each source alone with the strict flags (and -D each of `defines`); a failure is a UserError at the
    rendered line."""
    objects = []
    for source in sources:
        obj = folder / (source[:-2] + ".o")
        cmd = [*_compiler(), *C_FLAGS, *(f"-D{d}" for d in defines), "-I", str(folder), "-c", source, "-o", obj.name]
        done = subprocess.run(cmd, cwd=folder, capture_output=True, text=True)
        if done.returncode:
            found = _DIAGNOSTIC.search(done.stderr)
            location = None
            message = done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "compiler failed"
            if found:
                location = Location(f"native/{Path(found['file']).name}", int(found["line"]), int(found["col"]))
                message = found["msg"]
            raise UserError(
                f"the C kernel does not compile: {message}",
                location=location,
                hint=f"rendered sources kept in {folder}; compiler said:\n{done.stderr.strip()}",
            )
        objects.append(obj)
    return objects


class HostKernel:
    """The compiled kernel of one board: cffi `ffi`/`lib`, plus NumPy-friendly wrappers."""

    def __init__(self, module, path: Path):
        self.ffi = module.ffi
        self.lib = module.lib
        self.path = path

    def default_config(self):
        cfg = self.ffi.new("dr_config *")
        self.lib.dr_config_init(cfg)
        return cfg

    def session(self, block=None, window=None, accel_lsb_per_g=None, gyro_lsb_per_dps=None, deadband_g=None,
                motion_threshold_g=None, axis_map=None) -> "KernelSession":
        """A fresh kernel state with the board's configuration, any parameter overridden."""
        return KernelSession(self, block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g,
                             motion_threshold_g, axis_map)

    def block_median(self, x, block: int) -> np.ndarray:
        """float32 medians of consecutive blocks of x (numpy.median semantics)."""
        work = np.array(x, dtype=np.float32).ravel()
        out = np.zeros(max(1, len(work) // max(block, 1)), dtype=np.float32)
        n = self.lib.dr_block_median(self.ffi.from_buffer("float[]", work), len(work), block,
                                     self.ffi.from_buffer("float[]", out))
        if n < 0:
            raise ValueError(f"{len(work)} values are not a whole number of blocks of {block}")
        return out[:n]

    def offset_latlon(self, lat_e7: int, lon_e7: int, east_m: float, north_m: float) -> tuple[int, int]:
        lat = self.ffi.new("int32_t *")
        lon = self.ffi.new("int32_t *")
        self.lib.dr_offset_latlon(int(lat_e7), int(lon_e7), float(east_m), float(north_m), lat, lon)
        return int(lat[0]), int(lon[0])


class KernelSession:
    """A dr_config, a dr_state and the scratch buffer, all owned here as the app owns them on the device."""

    def __init__(self, kernel: HostKernel, block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g,
                 motion_threshold_g, axis_map):
        self.kernel = kernel
        ffi, lib = kernel.ffi, kernel.lib
        self.cfg = kernel.default_config()
        if axis_map is not None:
            for i, (source, sign) in enumerate(axis_map):
                self.cfg.axis_source[i] = int(source)
                self.cfg.axis_sign[i] = float(sign)
        if any(v is not None for v in (block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g,
                                       motion_threshold_g)):
            from codegen.kernel.reference import STANDARD_GRAVITY

            b = self.cfg.block if block is None else int(block)
            n = window if window is not None else (b if block is not None else self.cfg.window)
            accel = accel_lsb_per_g if accel_lsb_per_g is not None else STANDARD_GRAVITY / self.cfg.accel_ms2_per_lsb
            gyro = gyro_lsb_per_dps if gyro_lsb_per_dps is not None else (
                np.pi / 180.0 / self.cfg.gyro_rads_per_lsb)
            dead = deadband_g if deadband_g is not None else self.cfg.deadband_ms2 / STANDARD_GRAVITY
            motion = motion_threshold_g if motion_threshold_g is not None else (
                np.sqrt(self.cfg.motion_limit_lsb2) / accel)
            code = lib.dr_config_set(self.cfg, b, int(n), accel, gyro, dead, motion)
            if code:
                raise ValueError(ERRORS.get(code, f"kernel error {code}"))
        self.state = ffi.new("dr_state *")
        lib.dr_state_init(self.state)
        self.scratch = ffi.new("float[]", 3 * self.cfg.block)
        self.out = ffi.new("float[6]")

    @property
    def block(self) -> int:
        return self.cfg.block

    @property
    def q(self) -> np.ndarray:
        return np.array(list(self.state.q), dtype=np.float32)

    @q.setter
    def q(self, value) -> None:
        for i, x in enumerate(np.asarray(value, dtype=np.float64).ravel()[:4]):
            self.state.q[i] = float(x)

    @property
    def v(self) -> np.ndarray:
        return np.array(list(self.state.v), dtype=np.float32)

    @property
    def gyro_bias_lsb(self) -> np.ndarray:
        return np.array(list(self.state.gyro_bias_lsb), dtype=np.float32)

    @gyro_bias_lsb.setter
    def gyro_bias_lsb(self, value) -> None:
        for i, x in enumerate(np.asarray(value, dtype=np.float64).ravel()[:3]):
            self.state.gyro_bias_lsb[i] = float(x)

    def set_velocity(self, ve: float, vn: float, vu: float) -> None:
        self.kernel.lib.dr_set_velocity(self.state, ve, vn, vu)

    def rotate_heading(self, cos_a: float, sin_a: float) -> None:
        self.kernel.lib.dr_rotate_heading(self.state, cos_a, sin_a)

    def calibrate(self, samples) -> bool:
        """Samples (M, 6) int16 at rest -> True if the device moved (the state is updated either way)."""
        raw = np.ascontiguousarray(np.asarray(samples).reshape(-1, 6), dtype=np.int16)
        code = self.kernel.lib.dr_calibrate(self.cfg, self.state, self.kernel.ffi.from_buffer("int16_t[]", raw),
                                            len(raw))
        if code < 0:
            raise ValueError(ERRORS.get(code, f"kernel error {code}"))
        return code == 1

    def process(self, samples, dt_us):
        """One window: samples (N, 6) int16, dt_us (N,) hold times in us.
        Returns (displacement (3,) m, velocity (3,) m/s, medians (N/b, 3) m/s^2 after the deadband), float32."""
        ffi = self.kernel.ffi
        raw = np.ascontiguousarray(np.asarray(samples).reshape(-1, 6), dtype=np.int16)
        dt = np.ascontiguousarray(np.asarray(dt_us).ravel(), dtype=np.int32)
        if len(dt) != len(raw):
            raise ValueError(f"{len(raw)} samples but {len(dt)} time steps")
        medians = np.zeros((max(1, len(raw) // self.block), 3), dtype=np.float32)
        code = self.kernel.lib.dr_process(self.cfg, self.state, self.scratch, ffi.from_buffer("int16_t[]", raw),
                                          ffi.from_buffer("int32_t[]", dt), len(raw), self.out,
                                          ffi.from_buffer("float[]", medians))
        if code:
            raise ValueError(ERRORS.get(code, f"kernel error {code}"))
        out = np.array(list(self.out), dtype=np.float32)
        return out[:3], out[3:], medians[: len(raw) // self.block]


def _build_key(files: dict[str, bytes], cdef: str) -> str:
    digest = hashlib.sha256()
    for name in sorted(files):
        digest.update(name.encode() + b"\0" + files[name] + b"\0")
    digest.update(cdef.encode())
    digest.update(" ".join(C_FLAGS).encode())
    digest.update(" ".join(_compiler()).encode())
    digest.update(sys.version.encode())
    digest.update(Path(__file__).read_bytes())
    return digest.hexdigest()[:20]


def _import(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_MODULES: dict[str, tuple[object, Path]] = {}


def build_module(prefix: str, files: dict[str, bytes], sources: tuple[str, ...], cdef: str, c_source: str,
                 defines: tuple[str, ...] = ()):
    """Compile `sources` (from `files`, name -> content; with -D each of `defines`) and a cffi API-mode wrapper
    declaring `cdef`, or find the result in the cache under the hash of everything that went in. Returns (module,
    path of the built library)."""
    import cffi

    key = _build_key(files, cdef + c_source + "\0".join(("",) + defines))
    if key in _MODULES:
        return _MODULES[key]
    name = f"{prefix}_{key}"
    home = cache_dir() / prefix.strip("_") / key
    built = list(home.glob(f"{name}*.so")) + list(home.glob(f"{name}*.pyd")) if home.is_dir() else []
    if not built:
        cache_dir().mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=f"build-{key}-", dir=cache_dir()))
        try:
            for file_name, content in files.items():
                (work / file_name).write_bytes(content)
            objects = _compile_objects(work, sources, defines)
            ffi = cffi.FFI()
            ffi.cdef(cdef)
            ffi.set_source(name, c_source, include_dirs=[str(work)], extra_objects=[str(o) for o in objects])
            library = Path(ffi.compile(tmpdir=str(work), verbose=False))
            home.parent.mkdir(parents=True, exist_ok=True)
            staging = Path(tempfile.mkdtemp(prefix=f"stage-{key}-", dir=home.parent))
            for file_name in files:
                shutil.copy2(work / file_name, staging / file_name)
            shutil.copy2(library, staging / library.name)
            try:
                os.replace(staging, home)  # atomic: a concurrent build of the same key wins or loses whole
            except OSError:
                shutil.rmtree(staging, ignore_errors=True)
        except UserError:
            raise
        except Exception as problem:  # compiler missing, linker failure
            raise UserError(f"cannot build the host kernel: {problem}",
                            hint=f"build folder kept in {work}; a C compiler (cc) and Python headers are needed")
        else:
            shutil.rmtree(work, ignore_errors=True)
        built = list(home.glob(f"{name}*.so")) + list(home.glob(f"{name}*.pyd"))
    _MODULES[key] = (_import(built[0], name), built[0])
    return _MODULES[key]


def load_kernel(loaded=None, files: Optional[dict[str, bytes]] = None) -> HostKernel:
    """Compile (or find in the cache) the kernel for a board (a codegen.board.loader.LoadedBoard; None = the default
    board), or for explicit `files` (name -> content, as kernel_sources returns)."""
    files = files if files is not None else kernel_sources(loaded)
    module, path = build_module(
        "_drkernel", files, KERNEL_SOURCES, CDEF, '#include "dr_kernel.h"\n#include "dr_median.h"\n#include "dr_geo.h"\n'
    )
    return HostKernel(module, path)
