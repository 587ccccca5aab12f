/* dr_kernel.c: see dr_kernel.h; codegen/kernel/reference.py is the specification. */
#include "dr_kernel.h"

#include "dr_board.h"
#include "dr_math.h"
#include "dr_median.h"

void dr_config_init(dr_config *cfg) {
    cfg->axis_source[0] = DR_AXIS_X_SOURCE;
    cfg->axis_source[1] = DR_AXIS_Y_SOURCE;
    cfg->axis_source[2] = DR_AXIS_Z_SOURCE;
    cfg->axis_sign[0] = DR_AXIS_X_SIGN;
    cfg->axis_sign[1] = DR_AXIS_Y_SIGN;
    cfg->axis_sign[2] = DR_AXIS_Z_SIGN;
    (void)dr_config_set(cfg, DR_BLOCK_SAMPLES, DR_WINDOW_SAMPLES, DR_ACCEL_LSB_PER_G, DR_GYRO_LSB_PER_DPS,
                        DR_DEADBAND_G, DR_MOTION_THRESHOLD_G);
}

int dr_config_set(dr_config *cfg, int32_t block, int32_t window, float accel_lsb_per_g, float gyro_lsb_per_dps,
                  float deadband_g, float motion_threshold_g) {
    int code = dr_params_check(block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g, motion_threshold_g);
    if (code != DR_OK) {
        return code;
    }
    dr_params_store(cfg, block, window, accel_lsb_per_g, gyro_lsb_per_dps, deadband_g, motion_threshold_g);
    return DR_OK;
}

void dr_state_init(dr_state *st) {
    dr_state_start(st);
}

/* Returns 1 if cfg can index samples and scratch safely (it may come from a caller's buffer), else 0. */
static int dr_config_usable(const dr_config *cfg) {
    int i;
    if (cfg->block < 1) {
        return 0;
    }
    for (i = 0; i < 3; i++) {
        if (cfg->axis_source[i] < 0 || cfg->axis_source[i] > 2) {
            return 0;
        }
    }
    return 1;
}

/* body[0..5] = sample s (sensor frame, counts) remapped to the body frame, as floats. */
static void dr_remap(const dr_config *cfg, const int16_t *s, float body[6]) {
    int i;
    for (i = 0; i < 3; i++) {
        int32_t src = cfg->axis_source[i];
        body[i] = cfg->axis_sign[i] * (float)s[src];
        body[3 + i] = cfg->axis_sign[i] * (float)s[3 + src];
    }
}

/* Samples per exact int32 partial sum of int16 counts (32768 * 32768 = 2^30). */
#define DR_SUM_CHUNK (32768)

int dr_calibrate(const dr_config *cfg, dr_state *st, const int16_t *samples, int32_t count) {
    float body[6];
    float total[6];
    float mean[6];
    float var[3];
    float inv_count, norm;
    int32_t k;
    int i, moved = 0;
    if (!dr_config_usable(cfg)) {
        return DR_ERR_RANGE;
    }
    if (count < 1) {
        return DR_ERR_COUNT;
    }
    /* explicit zeroing: an aggregate initialiser may become a memset call, which a native module cannot link */
    for (i = 0; i < 6; i++) {
        total[i] = 0.0f;
    }
    dr_sum_counts(samples, count, 6, DR_SUM_CHUNK, total);
    inv_count = dr_recip((float)count);
    /* the remap only permutes and negates, so it may be applied to the sums */
    for (i = 0; i < 3; i++) {
        int32_t src = cfg->axis_source[i];
        mean[i] = cfg->axis_sign[i] * (total[src] * inv_count);
        mean[3 + i] = cfg->axis_sign[i] * (total[3 + src] * inv_count);
        var[i] = 0.0f;
    }
    for (k = 0; k < count; k++) {
        dr_remap(cfg, samples + 6 * k, body);
        for (i = 0; i < 3; i++) {
            float d = body[i] - mean[i];
            var[i] += d * d;
        }
    }
    for (i = 0; i < 3; i++) {
        if (var[i] * inv_count > cfg->motion_limit_lsb2) {
            moved = 1;
        }
    }
    norm = dr_sqrt(mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2]);
    dr_quat_from_gravity(st->q, mean, norm);
    for (i = 0; i < 3; i++) {
        st->gyro_bias_lsb[i] = mean[3 + i];
        st->v[i] = 0.0f;
    }
    return moved ? DR_MOVED : DR_OK;
}

/* q <- q (x) exp(omega dt / 2) for body rate omega (rad/s) held dt (s), then back to unit length.
 * With h = omega dt / 2 and x2 = |h|^2: exp = [cos|h|, sin|h| h/|h|], by the series
 * cos = 1 - x2/2 + x2^2/24 and sin/|h| = 1 - x2/6 + x2^2/120 (truncation |h|^6/720: below 3e-11 for
 * |h| < 0.05 rad, 6e-10 at 2000 degree/s and 5 ms, far under float32's 6e-8); no sqrt, no trigonometry. */
static void dr_gyro_step(float q[4], const float omega[3], float dt) {
    float half = 0.5f * dt;
    float h[3];
    float x2, c, s, r[4], dq[4], n2;
    h[0] = omega[0] * half;
    h[1] = omega[1] * half;
    h[2] = omega[2] * half;
    x2 = h[0] * h[0] + h[1] * h[1] + h[2] * h[2];
    c = 1.0f - x2 * (0.5f - x2 * (1.0f / 24.0f));
    s = 1.0f - x2 * ((1.0f / 6.0f) - x2 * (1.0f / 120.0f));
    dq[0] = c;
    dq[1] = s * h[0];
    dq[2] = s * h[1];
    dq[3] = s * h[2];
    dr_quat_multiply(r, q, dq);
    /* |r| differs from 1 by rounding only, so one Newton step of 1/sqrt from 1 is exact to float32 */
    n2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3];
    n2 = 1.5f - 0.5f * n2;
    q[0] = r[0] * n2;
    q[1] = r[1] * n2;
    q[2] = r[2] * n2;
    q[3] = r[3] * n2;
}

int dr_process(const dr_config *cfg, dr_state *st, float *scratch, const int16_t *samples, const int32_t *dt_us,
               int32_t count, float out[6], float *medians) {
    const int32_t b = cfg->block;
    float *ae = scratch;
    float *an = scratch + b;
    float *au = scratch + 2 * b;
    float p[3] = {0.0f, 0.0f, 0.0f};
    float body[6], omega[3], a[3];
    int32_t start, rest, k, blocks = 0;
    int i;
    if (!dr_config_usable(cfg)) {
        return DR_ERR_RANGE;
    }
    if (count < 1) {
        return DR_ERR_COUNT;
    }
    for (rest = count; rest >= b; rest -= b) {
    }
    if (rest != 0) {
        return DR_ERR_COUNT;
    }
    for (start = 0; start < count; start += b) {
        int32_t block_us = 0;
        float t, m[3];
        for (k = 0; k < b; k++) {
            const int16_t *s = samples + 6 * (start + k);
            int32_t us = dt_us[start + k];
            dr_remap(cfg, s, body);
            body[0] *= cfg->accel_ms2_per_lsb;
            body[1] *= cfg->accel_ms2_per_lsb;
            body[2] *= cfg->accel_ms2_per_lsb;
            dr_quat_rotate(a, st->q, body);
            ae[k] = a[0];
            an[k] = a[1];
            au[k] = a[2] - DR_GRAVITY_MS2;
            for (i = 0; i < 3; i++) {
                omega[i] = (body[3 + i] - st->gyro_bias_lsb[i]) * cfg->gyro_rads_per_lsb;
            }
            dr_gyro_step(st->q, omega, (float)us * DR_S_PER_US);
            block_us += us;
        }
        m[0] = dr_median(ae, b);
        m[1] = dr_median(an, b);
        m[2] = dr_median(au, b);
        t = (float)block_us * DR_S_PER_US;
        for (i = 0; i < 3; i++) {
            if (dr_absf(m[i]) < cfg->deadband_ms2) {
                m[i] = 0.0f;
            }
            p[i] += st->v[i] * t + 0.5f * m[i] * t * t;
            st->v[i] += m[i] * t;
        }
        if (medians != 0) {
            float *dst = medians + 3 * blocks;
            dst[0] = m[0];
            dst[1] = m[1];
            dst[2] = m[2];
        }
        blocks++;
    }
    for (i = 0; i < 3; i++) {
        out[i] = p[i];
        out[3 + i] = st->v[i];
    }
    return DR_OK;
}

void dr_set_velocity(dr_state *st, float ve, float vn, float vu) {
    st->v[0] = ve;
    st->v[1] = vn;
    st->v[2] = vu;
}

void dr_rotate_heading(dr_state *st, float cos_a, float sin_a) {
    float k = dr_inv_sqrt(cos_a * cos_a + sin_a * sin_a);
    float c = cos_a * k, s = sin_a * k;
    float yaw[4], r[4];
    int i;
    if (k == 0.0f) {
        return;
    }
    /* half angle without cancellation: from the larger of cos(a/2) = sqrt((1 + c) / 2) and
     * |sin(a/2)| = sqrt((1 - c) / 2), the other by sin(a) = 2 sin(a/2) cos(a/2); cos(a/2) >= 0 */
    if (c >= 0.0f) {
        yaw[0] = dr_sqrt(0.5f * (1.0f + c));
        yaw[3] = s * 0.5f * dr_recip(yaw[0]);
    } else {
        yaw[3] = dr_sqrt(0.5f * (1.0f - c));
        if (s < 0.0f) {
            yaw[3] = -yaw[3];
        }
        yaw[0] = s * 0.5f * dr_recip(yaw[3]);
    }
    yaw[1] = 0.0f;
    yaw[2] = 0.0f;
    dr_quat_multiply(r, yaw, st->q);
    for (i = 0; i < 4; i++) {
        st->q[i] = r[i];
    }
    dr_quat_normalise(st->q);
}
