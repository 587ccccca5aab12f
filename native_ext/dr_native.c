/*
 * dr_native.c: the thin MicroPython binding of the kernel, module `dr_native` (API in API.md).
 *
 * One file, two builds: a dynamic native module (.mpy, Makefile, MICROPY_ENABLE_DYNRUNTIME) and a user C module
 * linked into the firmware (micropython.mk / micropython.cmake). Each function parses its buffers (array('f') state
 * and out, array('h') samples, array('i') intervals), calls the kernel and returns; nothing is allocated per sample.
 *
 * state buffer layout (floats): dr_state, dr_config, scratch 3 * block; the fused buffer: dr_fused_state,
 * dr_fused_config, dr_config; the eskf buffer (a board with algorithm.mode: eskf, DR_WITH_ESKF): dr_eskf_state,
 * dr_eskf_config, dr_config. Their lengths and the offsets the module exports (DR_HEADER_FLOATS, DR_STATE_Q, ...)
 * come from dr_layout.h, rendered from the declaration in codegen/kernel/layout.py (dr_eskf.h's hand-written
 * structs are checked against it here, at compile time).
 */
#if MICROPY_ENABLE_DYNRUNTIME
#include "py/dynruntime.h"
#else
#include "py/runtime.h"
#include "py/obj.h"
#endif

#include <stddef.h>

#include "dr_board.h"
#include "dr_eskf.h"
#include "dr_fused.h"
#include "dr_geo.h"
#include "dr_kernel.h"
#include "dr_median.h"

typedef char dr_header_is_state_and_config[DR_HEADER_FLOATS == DR_STATE_FLOATS + DR_CONFIG_FLOATS ? 1 : -1];
typedef char dr_fused_buffer_is_three_structs[
    DR_FUSED_BUFFER_FLOATS == DR_FUSED_STATE_FLOATS + DR_FUSED_CONFIG_FLOATS + DR_CONFIG_FLOATS ? 1 : -1];
typedef char dr_eskf_buffer_is_three_structs[
    DR_ESKF_BUFFER_FLOATS == DR_ESKF_STATE_FLOATS + DR_ESKF_CONFIG_FLOATS + DR_CONFIG_FLOATS ? 1 : -1];
DR_ESKF_LAYOUT_CHECKS

/* The buffer of obj with the given array typecode, or a TypeError. */
static void dr_get_array(mp_obj_t obj, mp_buffer_info_t *info, mp_uint_t flags, char typecode) {
    mp_get_buffer_raise(obj, info, flags);
    if (info->typecode != typecode) {
        switch (typecode) {
            case 'f':
                mp_raise_TypeError(MP_ERROR_TEXT("expected array('f')"));
            case 'h':
                mp_raise_TypeError(MP_ERROR_TEXT("expected array('h')"));
            default:
                mp_raise_TypeError(MP_ERROR_TEXT("expected array('i')"));
        }
    }
}

static mp_int_t dr_state_len(mp_int_t block) {
    return DR_HEADER_FLOATS + 3 * block;
}

/* 1 if a state buffer of `floats` floats holds the scratch of `block` (compared without overflowing 3 * block). */
static int dr_fits(mp_int_t floats, mp_int_t block) {
    return block >= 1 && block <= (floats - DR_HEADER_FLOATS) / 3;
}

/* The kernel structs inside a state buffer; checks its size against the block stored in it. */
static float *dr_unpack(mp_obj_t state_obj, dr_state **st, dr_config **cfg, mp_int_t *floats) {
    mp_buffer_info_t info;
    float *base;
    dr_get_array(state_obj, &info, MP_BUFFER_RW, 'f');
    *floats = (mp_int_t)(info.len / sizeof(float));
    if (*floats < (mp_int_t)DR_HEADER_FLOATS) {
        mp_raise_ValueError(MP_ERROR_TEXT("state buffer shorter than state_len(block)"));
    }
    base = (float *)info.buf;
    *st = (dr_state *)base;
    *cfg = (dr_config *)(base + DR_STATE_FLOATS);
    return base + DR_HEADER_FLOATS;
}

static void dr_raise(int code) {
    switch (code) {
        case DR_ERR_BLOCK:
            mp_raise_ValueError(MP_ERROR_TEXT("block must be at least 1"));
        case DR_ERR_WINDOW:
            mp_raise_ValueError(MP_ERROR_TEXT("window must be a positive multiple of block"));
        case DR_ERR_COUNT:
            mp_raise_ValueError(MP_ERROR_TEXT("sample count must be a positive multiple of block"));
        case DR_ERR_RANGE:
        default:
            mp_raise_ValueError(MP_ERROR_TEXT("ranges and threshold must be > 0, deadband >= 0"));
    }
}

static mp_obj_t dr_state_len_fn(mp_obj_t block_obj) {
    return mp_obj_new_int(dr_state_len(mp_obj_get_int(block_obj)));
}
static MP_DEFINE_CONST_FUN_OBJ_1(dr_state_len_obj, dr_state_len_fn);

/* init(state) or init(state, block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g, motion_threshold_g) */
static mp_obj_t dr_init_fn(size_t n_args, const mp_obj_t *args) {
    dr_state *st;
    dr_config *cfg;
    dr_config fresh;
    mp_int_t floats;
    (void)dr_unpack(args[0], &st, &cfg, &floats);
    /* validated on a local copy first, so a rejected init leaves the state as it was; the second set writes the
     * state's own config (a struct assignment would be a memcpy call, which a native module cannot link) */
    dr_config_init(&fresh);
    if (n_args == 7) {
        int code = dr_config_set(&fresh, mp_obj_get_int(args[1]), mp_obj_get_int(args[2]),
                                 (float)mp_obj_get_float(args[3]), (float)mp_obj_get_float(args[4]),
                                 (float)mp_obj_get_float(args[5]), (float)mp_obj_get_float(args[6]));
        if (code != DR_OK) {
            dr_raise(code);
        }
    } else if (n_args != 1) {
        mp_raise_TypeError(MP_ERROR_TEXT("init takes state, or state and 6 parameters"));
    }
    if (!dr_fits(floats, fresh.block)) {
        mp_raise_ValueError(MP_ERROR_TEXT("state buffer shorter than state_len(block)"));
    }
    dr_config_init(cfg);
    if (n_args == 7) {
        (void)dr_config_set(cfg, fresh.block, fresh.window, (float)mp_obj_get_float(args[3]),
                            (float)mp_obj_get_float(args[4]), (float)mp_obj_get_float(args[5]),
                            (float)mp_obj_get_float(args[6]));
    }
    dr_state_init(st);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_init_obj, 1, 7, dr_init_fn);

static mp_obj_t dr_calibrate_fn(mp_obj_t state_obj, mp_obj_t samples_obj) {
    dr_state *st;
    dr_config *cfg;
    mp_int_t floats;
    mp_buffer_info_t samples;
    int code;
    (void)dr_unpack(state_obj, &st, &cfg, &floats);
    dr_get_array(samples_obj, &samples, MP_BUFFER_READ, 'h');
    if (!dr_fits(floats, cfg->block)) {
        mp_raise_ValueError(MP_ERROR_TEXT("state not initialised by init() or shorter than state_len(block)"));
    }
    code = dr_calibrate(cfg, st, (const int16_t *)samples.buf, (int32_t)(samples.len / (6 * sizeof(int16_t))));
    if (code < 0) {
        dr_raise(code);
    }
    return mp_obj_new_int(code);
}
static MP_DEFINE_CONST_FUN_OBJ_2(dr_calibrate_obj, dr_calibrate_fn);

static mp_obj_t dr_process_fn(size_t n_args, const mp_obj_t *args) {
    dr_state *st;
    dr_config *cfg;
    mp_int_t floats, count;
    mp_buffer_info_t samples, dt, out;
    float *scratch;
    int code;
    (void)n_args;
    scratch = dr_unpack(args[0], &st, &cfg, &floats);
    dr_get_array(args[1], &samples, MP_BUFFER_READ, 'h');
    dr_get_array(args[2], &dt, MP_BUFFER_READ, 'i');
    dr_get_array(args[3], &out, MP_BUFFER_RW, 'f');
    if (!dr_fits(floats, cfg->block)) {
        mp_raise_ValueError(MP_ERROR_TEXT("state not initialised by init() or shorter than state_len(block)"));
    }
    count = (mp_int_t)(samples.len / (6 * sizeof(int16_t)));
    if (samples.len != (size_t)count * 6 * sizeof(int16_t) || dt.len != (size_t)count * sizeof(int32_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("samples must hold 6 values and dt_us 1 value per sample"));
    }
    if (out.len < DR_OUT_FLOATS * sizeof(float)) {
        mp_raise_ValueError(MP_ERROR_TEXT("out must hold OUT_LEN floats"));
    }
    code = dr_process(cfg, st, scratch, (const int16_t *)samples.buf, (const int32_t *)dt.buf, (int32_t)count,
                      (float *)out.buf, 0);
    if (code != DR_OK) {
        dr_raise(code);
    }
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_process_obj, 4, 4, dr_process_fn);

static mp_obj_t dr_set_velocity_fn(size_t n_args, const mp_obj_t *args) {
    dr_state *st;
    dr_config *cfg;
    mp_int_t floats;
    (void)n_args;
    (void)dr_unpack(args[0], &st, &cfg, &floats);
    dr_set_velocity(st, (float)mp_obj_get_float(args[1]), (float)mp_obj_get_float(args[2]),
                    (float)mp_obj_get_float(args[3]));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_set_velocity_obj, 4, 4, dr_set_velocity_fn);

static mp_obj_t dr_rotate_heading_fn(mp_obj_t state_obj, mp_obj_t cos_obj, mp_obj_t sin_obj) {
    dr_state *st;
    dr_config *cfg;
    mp_int_t floats;
    (void)dr_unpack(state_obj, &st, &cfg, &floats);
    dr_rotate_heading(st, (float)mp_obj_get_float(cos_obj), (float)mp_obj_get_float(sin_obj));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_3(dr_rotate_heading_obj, dr_rotate_heading_fn);

static mp_obj_t dr_offset_latlon_fn(size_t n_args, const mp_obj_t *args) {
    int32_t lat, lon;
    mp_obj_t result[2];
    (void)n_args;
    dr_offset_latlon((int32_t)mp_obj_get_int(args[0]), (int32_t)mp_obj_get_int(args[1]),
                     (float)mp_obj_get_float(args[2]), (float)mp_obj_get_float(args[3]), &lat, &lon);
    result[0] = mp_obj_new_int(lat);
    result[1] = mp_obj_new_int(lon);
    return mp_obj_new_tuple(2, result);
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_offset_latlon_obj, 4, 4, dr_offset_latlon_fn);

static mp_obj_t dr_block_median_fn(mp_obj_t values_obj, mp_obj_t block_obj, mp_obj_t out_obj) {
    mp_buffer_info_t values, out;
    mp_int_t block = mp_obj_get_int(block_obj);
    int32_t count;
    dr_get_array(values_obj, &values, MP_BUFFER_RW, 'f');
    dr_get_array(out_obj, &out, MP_BUFFER_RW, 'f');
    count = (int32_t)(values.len / sizeof(float));
    if (block < 1 || (count / block) * (mp_int_t)sizeof(float) > (mp_int_t)out.len) {
        mp_raise_ValueError(MP_ERROR_TEXT("block must be >= 1 and out hold len(values) // block floats"));
    }
    if (dr_block_median((float *)values.buf, count, (int32_t)block, (float *)out.buf) < 0) {
        dr_raise(DR_ERR_COUNT);
    }
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_3(dr_block_median_obj, dr_block_median_fn);

/* ---- algorithm: fused (dr_fused.h). Its own state buffer: dr_fused_state | dr_fused_config | dr_config. ---- */

static void dr_fused_unpack(mp_obj_t obj, dr_fused_state **st, dr_fused_config **cfg, dr_config **kcfg) {
    mp_buffer_info_t info;
    float *base;
    dr_get_array(obj, &info, MP_BUFFER_RW, 'f');
    if ((mp_int_t)(info.len / sizeof(float)) < (mp_int_t)DR_FUSED_BUFFER_FLOATS) {
        mp_raise_ValueError(MP_ERROR_TEXT("fused state buffer shorter than FUSED_STATE_LEN"));
    }
    base = (float *)info.buf;
    *st = (dr_fused_state *)base;
    *cfg = (dr_fused_config *)(base + DR_FUSED_CONFIG_AT);
    *kcfg = (dr_config *)(base + DR_FUSED_KERNEL_CONFIG_AT);
}

/* fused_init(fstate): the board's configuration, a fresh state */
static mp_obj_t dr_fused_init_fn(mp_obj_t state_obj) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    dr_fused_unpack(state_obj, &st, &cfg, &kcfg);
    dr_config_init(kcfg);
    dr_fused_config_init(cfg);
    dr_fused_state_init(st);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(dr_fused_init_obj, dr_fused_init_fn);

static mp_obj_t dr_fused_calibrate_fn(mp_obj_t state_obj, mp_obj_t samples_obj) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    mp_buffer_info_t samples;
    int code;
    dr_fused_unpack(state_obj, &st, &cfg, &kcfg);
    dr_get_array(samples_obj, &samples, MP_BUFFER_READ, 'h');
    code = dr_fused_calibrate(kcfg, st, (const int16_t *)samples.buf, (int32_t)(samples.len / (6 * sizeof(int16_t))));
    if (code < 0) {
        dr_raise(code);
    }
    return mp_obj_new_int(code);
}
static MP_DEFINE_CONST_FUN_OBJ_2(dr_fused_calibrate_obj, dr_fused_calibrate_fn);

static mp_obj_t dr_fused_process_fn(size_t n_args, const mp_obj_t *args) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    mp_buffer_info_t samples, dt, out;
    mp_int_t count;
    (void)n_args;
    dr_fused_unpack(args[0], &st, &cfg, &kcfg);
    dr_get_array(args[1], &samples, MP_BUFFER_READ, 'h');
    dr_get_array(args[2], &dt, MP_BUFFER_READ, 'i');
    dr_get_array(args[3], &out, MP_BUFFER_RW, 'f');
    count = (mp_int_t)(samples.len / (6 * sizeof(int16_t)));
    if (count < 1 || samples.len != (size_t)count * 6 * sizeof(int16_t) || dt.len != (size_t)count * sizeof(int32_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("samples must hold 6 values and dt_us 1 value per sample"));
    }
    if (out.len < DR_OUT_FLOATS * sizeof(float)) {
        mp_raise_ValueError(MP_ERROR_TEXT("out must hold OUT_LEN floats"));
    }
    (void)dr_fused_process(kcfg, cfg, st, (const int16_t *)samples.buf, (const int32_t *)dt.buf, (int32_t)count,
                           (float *)out.buf);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_fused_process_obj, 4, 4, dr_fused_process_fn);

static mp_obj_t dr_fused_gps_fn(mp_obj_t state_obj, mp_obj_t ve_obj, mp_obj_t vn_obj) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    dr_fused_unpack(state_obj, &st, &cfg, &kcfg);
    dr_fused_gps(cfg, st, (float)mp_obj_get_float(ve_obj), (float)mp_obj_get_float(vn_obj));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_3(dr_fused_gps_obj, dr_fused_gps_fn);

/* The floats of a kept-state buffer (array('f') of at least FUSED_KEPT_LEN), or a ValueError. */
static float *dr_fused_kept_floats(mp_obj_t kept_obj, mp_uint_t flags) {
    mp_buffer_info_t kept;
    dr_get_array(kept_obj, &kept, flags, 'f');
    if (kept.len < DR_FUSED_KEPT_LEN * sizeof(float)) {
        mp_raise_ValueError(MP_ERROR_TEXT("kept must hold FUSED_KEPT_LEN floats"));
    }
    return (float *)kept.buf;
}

/* fused_keep(fstate, kept): what a reset should not lose, into kept */
static mp_obj_t dr_fused_keep_fn(mp_obj_t state_obj, mp_obj_t kept_obj) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    dr_fused_unpack(state_obj, &st, &cfg, &kcfg);
    dr_fused_keep(st, dr_fused_kept_floats(kept_obj, MP_BUFFER_WRITE));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(dr_fused_keep_obj, dr_fused_keep_fn);

/* fused_restore(fstate, kept): after a calibration that moved, takes up what fused_keep kept before a reset */
static mp_obj_t dr_fused_restore_fn(mp_obj_t state_obj, mp_obj_t kept_obj) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    dr_fused_unpack(state_obj, &st, &cfg, &kcfg);
    dr_fused_restore(cfg, st, dr_fused_kept_floats(kept_obj, MP_BUFFER_READ));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_2(dr_fused_restore_obj, dr_fused_restore_fn);

/* fused_position(fstate, ve, vn, de, dn): a fix's position, before fused_gps for the same fix */
static mp_obj_t dr_fused_position_fn(size_t n_args, const mp_obj_t *args) {
    dr_fused_state *st;
    dr_fused_config *cfg;
    dr_config *kcfg;
    (void)n_args;
    dr_fused_unpack(args[0], &st, &cfg, &kcfg);
    dr_fused_position(cfg, st, (float)mp_obj_get_float(args[1]), (float)mp_obj_get_float(args[2]),
                      (float)mp_obj_get_float(args[3]), (float)mp_obj_get_float(args[4]));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_fused_position_obj, 5, 5, dr_fused_position_fn);

#if DR_WITH_ESKF
/* ---- algorithm: eskf (dr_eskf.h). Its own state buffer: dr_eskf_state | dr_eskf_config | dr_config. ---- */

static void dr_eskf_unpack(mp_obj_t obj, dr_eskf_state **st, dr_eskf_config **cfg, dr_config **kcfg) {
    mp_buffer_info_t info;
    float *base;
    dr_get_array(obj, &info, MP_BUFFER_RW, 'f');
    if ((mp_int_t)(info.len / sizeof(float)) < (mp_int_t)DR_ESKF_BUFFER_FLOATS) {
        mp_raise_ValueError(MP_ERROR_TEXT("eskf state buffer shorter than ESKF_STATE_LEN"));
    }
    base = (float *)info.buf;
    *st = (dr_eskf_state *)base;
    *cfg = (dr_eskf_config *)(base + DR_ESKF_CONFIG_AT);
    *kcfg = (dr_config *)(base + DR_ESKF_KERNEL_CONFIG_AT);
}

/* The interleaved samples' count (6 int16 each), or a ValueError when the buffer holds a partial sample. */
static int32_t dr_sample_count(const mp_buffer_info_t *samples) {
    mp_int_t count = (mp_int_t)(samples->len / (6 * sizeof(int16_t)));
    if (samples->len != (size_t)count * 6 * sizeof(int16_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("samples must hold 6 values per sample"));
    }
    return (int32_t)count;
}

/* eskf_init(estate): the board's axis map and scales, the board's filter parameters, a fresh state */
static mp_obj_t dr_eskf_init_fn(mp_obj_t state_obj) {
    dr_eskf_state *st;
    dr_eskf_config *cfg;
    dr_config *kcfg;
    dr_eskf_unpack(state_obj, &st, &cfg, &kcfg);
    dr_config_init(kcfg);
    dr_eskf_config_init(cfg);
    DR_ESKF_CONFIG_BOARD(cfg);
    dr_eskf_state_init(st);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_1(dr_eskf_init_obj, dr_eskf_init_fn);

/* eskf_calibrate(estate, samples) -> 1 if the device moved during it, else 0 */
static mp_obj_t dr_eskf_calibrate_fn(mp_obj_t state_obj, mp_obj_t samples_obj) {
    dr_eskf_state *st;
    dr_eskf_config *cfg;
    dr_config *kcfg;
    mp_buffer_info_t samples;
    int code;
    dr_eskf_unpack(state_obj, &st, &cfg, &kcfg);
    dr_get_array(samples_obj, &samples, MP_BUFFER_READ, 'h');
    code = dr_eskf_calibrate(kcfg, cfg, st, (const int16_t *)samples.buf, dr_sample_count(&samples));
    if (code < 0) {
        mp_raise_ValueError(MP_ERROR_TEXT("calibration needs at least 1 sample with gravity in it"));
    }
    return mp_obj_new_int(code);
}
static MP_DEFINE_CONST_FUN_OBJ_2(dr_eskf_calibrate_obj, dr_eskf_calibrate_fn);

/* eskf_process(estate, samples, dt_us, out): out <- position E N U (m, the run's ENU), velocity E N U (m/s) */
static mp_obj_t dr_eskf_process_fn(size_t n_args, const mp_obj_t *args) {
    dr_eskf_state *st;
    dr_eskf_config *cfg;
    dr_config *kcfg;
    mp_buffer_info_t samples, dt, out;
    int32_t count;
    (void)n_args;
    dr_eskf_unpack(args[0], &st, &cfg, &kcfg);
    dr_get_array(args[1], &samples, MP_BUFFER_READ, 'h');
    dr_get_array(args[2], &dt, MP_BUFFER_READ, 'i');
    dr_get_array(args[3], &out, MP_BUFFER_RW, 'f');
    count = dr_sample_count(&samples);
    if (count < 1 || dt.len != (size_t)count * sizeof(int32_t)) {
        mp_raise_ValueError(MP_ERROR_TEXT("samples must hold 6 values and dt_us 1 value per sample"));
    }
    if (out.len < DR_OUT_FLOATS * sizeof(float)) {
        mp_raise_ValueError(MP_ERROR_TEXT("out must hold OUT_LEN floats"));
    }
    (void)dr_eskf_process(kcfg, cfg, st, (const int16_t *)samples.buf, (const int32_t *)dt.buf, count,
                          (float *)out.buf);
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_eskf_process_obj, 4, 4, dr_eskf_process_fn);

/* eskf_gps(estate, t_s, e, n, u, ve, vn) -> 1 if the filter started at this fix, else 0 */
static mp_obj_t dr_eskf_gps_fn(size_t n_args, const mp_obj_t *args) {
    dr_eskf_state *st;
    dr_eskf_config *cfg;
    dr_config *kcfg;
    (void)n_args;
    dr_eskf_unpack(args[0], &st, &cfg, &kcfg);
    return mp_obj_new_int(dr_eskf_gps(cfg, st, (float)mp_obj_get_float(args[1]), (float)mp_obj_get_float(args[2]),
                                      (float)mp_obj_get_float(args[3]), (float)mp_obj_get_float(args[4]),
                                      (float)mp_obj_get_float(args[5]), (float)mp_obj_get_float(args[6])));
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_eskf_gps_obj, 7, 7, dr_eskf_gps_fn);

/* eskf_calibration_interval(estate, ve, vn, seconds) -> None: the fix `seconds` before the calibration's end */
static mp_obj_t dr_eskf_calibration_interval_fn(size_t n_args, const mp_obj_t *args) {
    dr_eskf_state *st;
    dr_eskf_config *cfg;
    dr_config *kcfg;
    (void)n_args;
    dr_eskf_unpack(args[0], &st, &cfg, &kcfg);
    dr_eskf_calibration_interval(st, (float)mp_obj_get_float(args[1]), (float)mp_obj_get_float(args[2]),
                                 (float)mp_obj_get_float(args[3]));
    return mp_const_none;
}
static MP_DEFINE_CONST_FUN_OBJ_VAR_BETWEEN(dr_eskf_calibration_interval_obj, 4, 4, dr_eskf_calibration_interval_fn);
#endif /* DR_WITH_ESKF */

#if MICROPY_ENABLE_DYNRUNTIME

mp_obj_t mpy_init(mp_obj_fun_bc_t *self, size_t n_args, size_t n_kw, mp_obj_t *args) {
    MP_DYNRUNTIME_INIT_ENTRY
    mp_store_global(MP_QSTR_state_len, MP_OBJ_FROM_PTR(&dr_state_len_obj));
    mp_store_global(MP_QSTR_init, MP_OBJ_FROM_PTR(&dr_init_obj));
    mp_store_global(MP_QSTR_calibrate, MP_OBJ_FROM_PTR(&dr_calibrate_obj));
    mp_store_global(MP_QSTR_process, MP_OBJ_FROM_PTR(&dr_process_obj));
    mp_store_global(MP_QSTR_set_velocity, MP_OBJ_FROM_PTR(&dr_set_velocity_obj));
    mp_store_global(MP_QSTR_rotate_heading, MP_OBJ_FROM_PTR(&dr_rotate_heading_obj));
    mp_store_global(MP_QSTR_offset_latlon, MP_OBJ_FROM_PTR(&dr_offset_latlon_obj));
    mp_store_global(MP_QSTR_block_median, MP_OBJ_FROM_PTR(&dr_block_median_obj));
    mp_store_global(MP_QSTR_STATE_LEN, MP_OBJ_NEW_SMALL_INT(dr_state_len(DR_BLOCK_SAMPLES)));
    mp_store_global(MP_QSTR_OUT_LEN, MP_OBJ_NEW_SMALL_INT(DR_OUT_FLOATS));
    mp_store_global(MP_QSTR_BLOCK, MP_OBJ_NEW_SMALL_INT(DR_BLOCK_SAMPLES));
    mp_store_global(MP_QSTR_WINDOW, MP_OBJ_NEW_SMALL_INT(DR_WINDOW_SAMPLES));
    mp_store_global(MP_QSTR_CALIBRATION_SAMPLES, MP_OBJ_NEW_SMALL_INT(DR_CALIBRATION_SAMPLES));
    mp_store_global(MP_QSTR_Q, MP_OBJ_NEW_SMALL_INT(DR_STATE_Q));
    mp_store_global(MP_QSTR_V, MP_OBJ_NEW_SMALL_INT(DR_STATE_V));
    mp_store_global(MP_QSTR_GYRO_BIAS, MP_OBJ_NEW_SMALL_INT(DR_STATE_GYRO_BIAS_LSB));
    mp_store_global(MP_QSTR_fused_init, MP_OBJ_FROM_PTR(&dr_fused_init_obj));
    mp_store_global(MP_QSTR_fused_calibrate, MP_OBJ_FROM_PTR(&dr_fused_calibrate_obj));
    mp_store_global(MP_QSTR_fused_process, MP_OBJ_FROM_PTR(&dr_fused_process_obj));
    mp_store_global(MP_QSTR_fused_gps, MP_OBJ_FROM_PTR(&dr_fused_gps_obj));
    mp_store_global(MP_QSTR_fused_position, MP_OBJ_FROM_PTR(&dr_fused_position_obj));
    mp_store_global(MP_QSTR_fused_keep, MP_OBJ_FROM_PTR(&dr_fused_keep_obj));
    mp_store_global(MP_QSTR_fused_restore, MP_OBJ_FROM_PTR(&dr_fused_restore_obj));
    mp_store_global(MP_QSTR_FUSED_KEPT_LEN, MP_OBJ_NEW_SMALL_INT(DR_FUSED_KEPT_LEN));
    mp_store_global(MP_QSTR_FUSED_GYRO_BIAS, MP_OBJ_NEW_SMALL_INT(DR_FUSED_STATE_GYRO_BIAS_LSB));
    mp_store_global(MP_QSTR_CAL_MOVED, MP_OBJ_NEW_SMALL_INT(DR_FUSED_STATE_CAL_MOVED));
    mp_store_global(MP_QSTR_FIX_AE, MP_OBJ_NEW_SMALL_INT(DR_FUSED_STATE_FIX_AE));
    mp_store_global(MP_QSTR_COV_REPAIRS, MP_OBJ_NEW_SMALL_INT(DR_FUSED_STATE_COV_REPAIRS));
    mp_store_global(MP_QSTR_FUSED_STATE_LEN, MP_OBJ_NEW_SMALL_INT(DR_FUSED_BUFFER_FLOATS));
#if DR_WITH_ESKF
    mp_store_global(MP_QSTR_eskf_init, MP_OBJ_FROM_PTR(&dr_eskf_init_obj));
    mp_store_global(MP_QSTR_eskf_calibrate, MP_OBJ_FROM_PTR(&dr_eskf_calibrate_obj));
    mp_store_global(MP_QSTR_eskf_process, MP_OBJ_FROM_PTR(&dr_eskf_process_obj));
    mp_store_global(MP_QSTR_eskf_gps, MP_OBJ_FROM_PTR(&dr_eskf_gps_obj));
    mp_store_global(MP_QSTR_eskf_calibration_interval, MP_OBJ_FROM_PTR(&dr_eskf_calibration_interval_obj));
    mp_store_global(MP_QSTR_ESKF_STATE_LEN, MP_OBJ_NEW_SMALL_INT(DR_ESKF_BUFFER_FLOATS));
    mp_store_global(MP_QSTR_ESKF_POS, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_POS));
    mp_store_global(MP_QSTR_ESKF_VEL, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_VEL));
    mp_store_global(MP_QSTR_ESKF_Q, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_Q));
    mp_store_global(MP_QSTR_ESKF_ALIGNED, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_ALIGNED));
    mp_store_global(MP_QSTR_ESKF_GPS_SPEED, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_GPS_SPEED));
    mp_store_global(MP_QSTR_ESKF_COV_REPAIRS, MP_OBJ_NEW_SMALL_INT(DR_ESKF_STATE_COV_REPAIRS));
#endif
    MP_DYNRUNTIME_INIT_EXIT
}

#else

static const mp_rom_map_elem_t dr_native_globals_table[] = {
    { MP_ROM_QSTR(MP_QSTR___name__), MP_ROM_QSTR(MP_QSTR_dr_native) },
    { MP_ROM_QSTR(MP_QSTR_state_len), MP_ROM_PTR(&dr_state_len_obj) },
    { MP_ROM_QSTR(MP_QSTR_init), MP_ROM_PTR(&dr_init_obj) },
    { MP_ROM_QSTR(MP_QSTR_calibrate), MP_ROM_PTR(&dr_calibrate_obj) },
    { MP_ROM_QSTR(MP_QSTR_process), MP_ROM_PTR(&dr_process_obj) },
    { MP_ROM_QSTR(MP_QSTR_set_velocity), MP_ROM_PTR(&dr_set_velocity_obj) },
    { MP_ROM_QSTR(MP_QSTR_rotate_heading), MP_ROM_PTR(&dr_rotate_heading_obj) },
    { MP_ROM_QSTR(MP_QSTR_offset_latlon), MP_ROM_PTR(&dr_offset_latlon_obj) },
    { MP_ROM_QSTR(MP_QSTR_block_median), MP_ROM_PTR(&dr_block_median_obj) },
    { MP_ROM_QSTR(MP_QSTR_STATE_LEN), MP_ROM_INT(DR_HEADER_FLOATS + 3 * DR_BLOCK_SAMPLES) },
    { MP_ROM_QSTR(MP_QSTR_OUT_LEN), MP_ROM_INT(DR_OUT_FLOATS) },
    { MP_ROM_QSTR(MP_QSTR_BLOCK), MP_ROM_INT(DR_BLOCK_SAMPLES) },
    { MP_ROM_QSTR(MP_QSTR_WINDOW), MP_ROM_INT(DR_WINDOW_SAMPLES) },
    { MP_ROM_QSTR(MP_QSTR_CALIBRATION_SAMPLES), MP_ROM_INT(DR_CALIBRATION_SAMPLES) },
    { MP_ROM_QSTR(MP_QSTR_Q), MP_ROM_INT(DR_STATE_Q) },
    { MP_ROM_QSTR(MP_QSTR_V), MP_ROM_INT(DR_STATE_V) },
    { MP_ROM_QSTR(MP_QSTR_GYRO_BIAS), MP_ROM_INT(DR_STATE_GYRO_BIAS_LSB) },
    { MP_ROM_QSTR(MP_QSTR_fused_init), MP_ROM_PTR(&dr_fused_init_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_calibrate), MP_ROM_PTR(&dr_fused_calibrate_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_process), MP_ROM_PTR(&dr_fused_process_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_gps), MP_ROM_PTR(&dr_fused_gps_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_position), MP_ROM_PTR(&dr_fused_position_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_keep), MP_ROM_PTR(&dr_fused_keep_obj) },
    { MP_ROM_QSTR(MP_QSTR_fused_restore), MP_ROM_PTR(&dr_fused_restore_obj) },
    { MP_ROM_QSTR(MP_QSTR_FUSED_KEPT_LEN), MP_ROM_INT(DR_FUSED_KEPT_LEN) },
    { MP_ROM_QSTR(MP_QSTR_FUSED_GYRO_BIAS), MP_ROM_INT(DR_FUSED_STATE_GYRO_BIAS_LSB) },
    { MP_ROM_QSTR(MP_QSTR_CAL_MOVED), MP_ROM_INT(DR_FUSED_STATE_CAL_MOVED) },
    { MP_ROM_QSTR(MP_QSTR_FIX_AE), MP_ROM_INT(DR_FUSED_STATE_FIX_AE) },
    { MP_ROM_QSTR(MP_QSTR_COV_REPAIRS), MP_ROM_INT(DR_FUSED_STATE_COV_REPAIRS) },
    { MP_ROM_QSTR(MP_QSTR_FUSED_STATE_LEN), MP_ROM_INT(DR_FUSED_BUFFER_FLOATS) },
#if DR_WITH_ESKF
    { MP_ROM_QSTR(MP_QSTR_eskf_init), MP_ROM_PTR(&dr_eskf_init_obj) },
    { MP_ROM_QSTR(MP_QSTR_eskf_calibrate), MP_ROM_PTR(&dr_eskf_calibrate_obj) },
    { MP_ROM_QSTR(MP_QSTR_eskf_process), MP_ROM_PTR(&dr_eskf_process_obj) },
    { MP_ROM_QSTR(MP_QSTR_eskf_gps), MP_ROM_PTR(&dr_eskf_gps_obj) },
    { MP_ROM_QSTR(MP_QSTR_eskf_calibration_interval), MP_ROM_PTR(&dr_eskf_calibration_interval_obj) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_STATE_LEN), MP_ROM_INT(DR_ESKF_BUFFER_FLOATS) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_POS), MP_ROM_INT(DR_ESKF_STATE_POS) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_VEL), MP_ROM_INT(DR_ESKF_STATE_VEL) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_Q), MP_ROM_INT(DR_ESKF_STATE_Q) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_ALIGNED), MP_ROM_INT(DR_ESKF_STATE_ALIGNED) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_GPS_SPEED), MP_ROM_INT(DR_ESKF_STATE_GPS_SPEED) },
    { MP_ROM_QSTR(MP_QSTR_ESKF_COV_REPAIRS), MP_ROM_INT(DR_ESKF_STATE_COV_REPAIRS) },
#endif
};
static MP_DEFINE_CONST_DICT(dr_native_globals, dr_native_globals_table);

const mp_obj_module_t dr_native_user_cmodule = {
    .base = { &mp_type_module },
    .globals = (mp_obj_dict_t *)&dr_native_globals,
};

MP_REGISTER_MODULE(MP_QSTR_dr_native, dr_native_user_cmodule);

#endif
