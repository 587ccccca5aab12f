/*
 * dr_fused.c: the fused real-time algorithm; see dr_fused.h and codegen/kernel/fused.py (the specification).
 */
#include "dr_fused.h"

#include "dr_board.h"
#include "dr_math.h"
#include "dr_median.h"

#define DR_FUSED_SUM_CHUNK (1024) /* samples summed in int32 before moving to float (1024 * 32768 < 2^31) */
#define DR_FUSED_COV_MAX (1.0e30f) /* a covariance entry beyond this in magnitude (or not a number) is broken */

/* After every step of every filter, a host build with DR_FUSED_OBSERVED defined (codegen/kernel/hostfused.py) calls
 * dr_fused_observed(st, DR_FUSED_FILTER_*, DR_FUSED_STEP_*) before the covariance is checked; on the device the
 * hook is nothing. */
#ifdef DR_FUSED_OBSERVED
void dr_fused_observed(const dr_fused_state *st, int filter, int step);
#define DR_FUSED_OBSERVE(st, filter, step) dr_fused_observed((st), (filter), (step))
#else
#define DR_FUSED_OBSERVE(st, filter, step) ((void)(st), (void)(filter), (void)(step))
#endif

void dr_fused_config_init(dr_fused_config *cfg) {
    float p[DR_FUSED_PARAMS];
    dr_fused_params_board(p);
    (void)dr_fused_config_set(cfg, p);
}

int dr_fused_config_set(dr_fused_config *cfg, const float p[DR_FUSED_PARAMS]) {
    int code = dr_fused_params_check(p);
    if (code != DR_OK) {
        return code;
    }
    dr_fused_params_store(cfg, p);
    return DR_OK;
}

void dr_fused_state_init(dr_fused_state *st) {
    dr_fused_state_start(st);
}

int dr_fused_calibrate(const dr_config *kcfg, dr_fused_state *st, const int16_t *samples, int32_t count) {
    dr_state seed;
    float total[3];
    float inv_count, m2;
    int32_t k, chunk;
    int i, code;
    dr_state_init(&seed);
    code = dr_calibrate(kcfg, &seed, samples, count);
    if (code < 0) {
        return code;
    }
    for (i = 0; i < 3; i++) {
        total[i] = 0.0f;
    }
    for (k = 0; k < count; k += chunk) {
        int32_t sum[3];
        int32_t j;
        for (i = 0; i < 3; i++) {
            sum[i] = 0;
        }
        chunk = count - k < DR_FUSED_SUM_CHUNK ? count - k : DR_FUSED_SUM_CHUNK;
        for (j = k; j < k + chunk; j++) {
            for (i = 0; i < 3; i++) {
                sum[i] += samples[6 * j + i];
            }
        }
        for (i = 0; i < 3; i++) {
            total[i] += (float)sum[i];
        }
    }
    inv_count = dr_recip((float)count);
    m2 = 0.0f;
    for (i = 0; i < 3; i++) {
        float m = total[i] * inv_count;
        m2 += m * m;
    }
    for (i = 0; i < 4; i++) {
        st->q[i] = seed.q[i];
    }
    for (i = 0; i < 3; i++) {
        st->gyro_bias_lsb[i] = seed.gyro_bias_lsb[i];
    }
    st->mean_f = dr_sqrt(m2) * kcfg->accel_ms2_per_lsb;
    st->var_f = 0.0f;
    st->vib_var = 0.0f;
    st->vib_tot = 0.0f;
    st->vib_lp[0] = st->mean_f;
    st->vib_lp[1] = 0.0f;
    for (i = 0; i < 3; i++) {
        st->ws[i] = 0.0f;
    }
    st->rest_s = 0.0f;
    st->speed = 0.0f;
    st->bax = 0.0f;
    st->bay = 0.0f;
    st->baz = 0.0f;
    return code;
}

/* The tilt/offset filter's covariance as a full 5 x 5 matrix: the 4 x 4 block's upper triangle (st->p, row by row)
 * and the fifth column (st->pz). */
static void dr_fused_p_load(const dr_fused_state *st, float pm[5][5]) {
    int i, j, n = 0;
    for (i = 0; i < 4; i++) {
        for (j = i; j < 4; j++) {
            pm[i][j] = st->p[n];
            pm[j][i] = st->p[n];
            n++;
        }
    }
    for (i = 0; i < 5; i++) {
        pm[i][4] = st->pz[i];
        pm[4][i] = st->pz[i];
    }
}

static void dr_fused_p_store(dr_fused_state *st, float pm[5][5]) {
    int i, j, n = 0;
    for (i = 0; i < 4; i++) {
        for (j = i; j < 4; j++) {
            st->p[n++] = pm[i][j];
        }
    }
    for (i = 0; i < 5; i++) {
        st->pz[i] = pm[i][4];
    }
}

/* The rows of R(q) (body -> kernel ENU): r[i][j] for i, j in 0..2. */
static void dr_fused_rotation(const float q[4], float r[3][3]) {
    float qw = q[0], qx = q[1], qy = q[2], qz = q[3];
    r[0][0] = 1.0f - 2.0f * (qy * qy + qz * qz);
    r[0][1] = 2.0f * (qx * qy - qw * qz);
    r[0][2] = 2.0f * (qx * qz + qw * qy);
    r[1][0] = 2.0f * (qx * qy + qw * qz);
    r[1][1] = 1.0f - 2.0f * (qx * qx + qz * qz);
    r[1][2] = 2.0f * (qy * qz - qw * qx);
    r[2][0] = 2.0f * (qx * qz - qw * qy);
    r[2][1] = 2.0f * (qy * qz + qw * qx);
    r[2][2] = 1.0f - 2.0f * (qx * qx + qy * qy);
}

/* The tilt/offset filter's covariance at its start (codegen.fused's _kf_prior): b ~ kf_bias_init_g per axis across
 * gravity (0 along it), d = -R_h b, from the attitude st->q. */
static void dr_fused_kf_prior(const dr_fused_config *cfg, dr_fused_state *st) {
    float r[3][3], pm[5][5];
    const float v = cfg->kf_bias_var;
    int i, j, c;
    dr_fused_rotation(st->q, r);
    for (i = 0; i < 5; i++) {
        for (j = i; j < 5; j++) {
            float value;
            if (j < 2) {
                value = 0.0f;
                for (c = 0; c < 3; c++) {
                    value += r[i][c] * r[j][c];
                }
                value *= v;
            } else if (i < 2) {
                value = -v * r[i][j - 2];
            } else { /* LLVM's Xtensa backend cannot select a constant pair (i == j ? 1.0f : 0.0f) */
                value = -v * r[2][i - 2] * r[2][j - 2];
                if (i == j) {
                    value += v;
                }
            }
            pm[i][j] = value;
            pm[j][i] = value;
        }
    }
    dr_fused_p_store(st, pm);
    st->kf_t = 0.0f;
    st->turn = 0.0f;
}

/* Whether a covariance entry is a number within +-DR_FUSED_COV_MAX (NaN fails both comparisons). */
static int dr_fused_bounded(float v) {
    return v <= DR_FUSED_COV_MAX && v >= -DR_FUSED_COV_MAX;
}

/* Whether the upper triangle p (n x n, row by row) is usable: every entry bounded, every variance >= 0. */
static int dr_fused_triangle_usable(const float *p, int n) {
    int i, j, k = 0;
    for (i = 0; i < n; i++) {
        for (j = i; j < n; j++) {
            if (!dr_fused_bounded(p[k]) || (j == i && !(p[k] >= 0.0f))) {
                return 0;
            }
            k++;
        }
    }
    return 1;
}

static void dr_fused_nhc_restart(dr_fused_state *st);
static void dr_fused_position_prior(const dr_fused_config *cfg, dr_fused_state *st);

/* After a step of a filter (codegen.fused's _covariance_checked): 1 if its covariance is usable (and, for an update,
 * innovation_ok: the innovation's covariance was positive definite); otherwise it is reset to its prior, counted in
 * st->cov_repairs, and 0 returned (the caller uses nothing of the step). */
static int dr_fused_covariance_checked(const dr_fused_config *cfg, dr_fused_state *st, int filter, int step,
                                       int innovation_ok) {
    int usable;
    DR_FUSED_OBSERVE(st, filter, step);
    if (!innovation_ok) {
        usable = 0;
    } else if (filter == DR_FUSED_FILTER_TILT) {
        usable = dr_fused_triangle_usable(st->p, 4) && dr_fused_bounded(st->pz[0]) && dr_fused_bounded(st->pz[1]) &&
                 dr_fused_bounded(st->pz[2]) && dr_fused_bounded(st->pz[3]) && dr_fused_triangle_usable(st->pz + 4, 1);
    } else if (filter == DR_FUSED_FILTER_LATERAL) {
        usable = dr_fused_triangle_usable(st->nh_p, 4);
    } else {
        usable = dr_fused_bounded(st->fix_pxx) && st->fix_pxx >= 0.0f && dr_fused_bounded(st->fix_pxe) &&
                 dr_fused_bounded(st->fix_pee) && st->fix_pee >= 0.0f;
    }
    if (usable) {
        return 1;
    }
    st->cov_repairs += 1.0f;
    if (filter == DR_FUSED_FILTER_TILT) {
        dr_fused_kf_prior(cfg, st);
    } else if (filter == DR_FUSED_FILTER_LATERAL) {
        dr_fused_nhc_restart(st);
    } else {
        dr_fused_position_prior(cfg, st);
    }
    return 0;
}

/* Starts the tilt/offset filter on its first use after calibration (codegen.fused's _kf_start). Returns 1 if it
 * started now (no update this time). */
static int dr_fused_kf_start(const dr_fused_config *cfg, dr_fused_state *st) {
    if (st->p[7] > 0.0f) {
        return 0;
    }
    dr_fused_kf_prior(cfg, st);
    dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_START, 1);
    return 1;
}

/* The filter's predict P <- P + Q, Q the process noise over the kf_t seconds since its last prediction
 * (codegen.fused's _kf_predict). Returns 0 if the covariance went wrong (reset to the prior). */
int dr_fused_kf_predict(const dr_fused_config *cfg, dr_fused_state *st) {
    float qd = cfg->kf_tilt_q * st->kf_t + cfg->kf_turn_q * st->turn * st->turn;
    float qb = cfg->kf_bias_q * st->kf_t;
    st->p[0] += qd;
    st->p[4] += qd;
    st->p[7] += qb;
    st->p[9] += qb;
    st->pz[4] += qb;
    st->kf_t = 0.0f;
    st->turn = 0.0f;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_PREDICT, 1);
}

/* The filter's update with z = d + h b + noise (variance r per axis), H = [I2 | h]: P <- P - K S K^T, fed back at
 * once (codegen.fused's _kf_update): b into bax, bay, baz, d as a small rotation of q about the kernel frame's
 * horizontal axes. x: the correction. Returns 0 if the covariance went wrong (reset to the prior, nothing fed back,
 * x unset). */
int dr_fused_kf_update(const dr_fused_config *cfg, dr_fused_state *st, float z0, float z1, const float h[2][3],
                       float r, float x[5]) {
    float pm[5][5], pht[5][2], gain[5][2];
    float s00, s01, s11, inv_det, i00, i01, i11, hx, hy;
    int i, j, c;
    dr_fused_p_load(st, pm);
    for (i = 0; i < 5; i++) { /* P H^T, H = [I2 | h] */
        for (j = 0; j < 2; j++) {
            pht[i][j] = pm[i][j];
            for (c = 0; c < 3; c++) {
                pht[i][j] += pm[i][2 + c] * h[j][c];
            }
        }
    }
    s00 = pht[0][0] + r;
    s01 = pht[0][1];
    s11 = pht[1][1] + r;
    for (c = 0; c < 3; c++) {
        s00 += h[0][c] * pht[2 + c][0];
        s01 += h[0][c] * pht[2 + c][1];
        s11 += h[1][c] * pht[2 + c][1];
    }
    if (!(s00 > 0.0f && s00 <= DR_FUSED_COV_MAX && s00 * s11 - s01 * s01 > 0.0f &&
          s00 * s11 - s01 * s01 <= DR_FUSED_COV_MAX)) {
        return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_UPDATE, 0);
    }
    inv_det = dr_recip(s00 * s11 - s01 * s01);
    i00 = s11 * inv_det;
    i01 = -s01 * inv_det;
    i11 = s00 * inv_det;
    for (i = 0; i < 5; i++) { /* K = P H^T S^-1, x = K z */
        gain[i][0] = pht[i][0] * i00 + pht[i][1] * i01;
        gain[i][1] = pht[i][0] * i01 + pht[i][1] * i11;
        x[i] = gain[i][0] * z0 + gain[i][1] * z1;
    }
    for (i = 0; i < 5; i++) {
        for (j = i; j < 5; j++) {
            pm[i][j] -= gain[i][0] * pht[j][0] + gain[i][1] * pht[j][1];
        }
    }
    for (i = 0; i < 5; i++) { /* the upper triangle is what is stored */
        for (j = 0; j < i; j++) {
            pm[i][j] = pm[j][i];
        }
    }
    dr_fused_p_store(st, pm);
    if (!dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_UPDATE, 1)) {
        return 0;
    }
    st->bax += x[2];
    st->bay += x[3];
    st->baz += x[4];
    /* remove the leak: q <- [1, (d_N / g, -d_E / g, 0) / 2] (x) q */
    hx = 0.5f * x[1] * DR_INV_GRAVITY;
    hy = -0.5f * x[0] * DR_INV_GRAVITY;
    {
        float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
        float nw = qw - hx * qx - hy * qy;
        float nx = qx + hx * qw + hy * qz;
        float ny = qy + hy * qw - hx * qz;
        float nz = qz + hx * qy - hy * qx;
        float inv = dr_inv_sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
        st->q[0] = nw * inv;
        st->q[1] = nx * inv;
        st->q[2] = ny * inv;
        st->q[3] = nz * inv;
    }
    return 1;
}

/* Every rest_update_s at rest (codegen.fused's rest_update): the smoothed rate is the gyro bias's error, the smoothed
 * horizontal specific force the tilt/offset filter's; both taken in. */
static void dr_fused_rest_update(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st) {
    float zt = st->zt, r[3][3], h[2][3], x[5];
    int i;
    st->zt = 0.0f;
    if (cfg->inv_bias_tau > 0.0f) {
        float k = zt * cfg->inv_bias_tau;
        k = (k < 1.0f ? k : 1.0f) * dr_recip(kcfg->gyro_rads_per_lsb);
        for (i = 0; i < 3; i++) {
            st->gyro_bias_lsb[i] += k * st->ws[i];
        }
    }
    if (!(cfg->kf_bias_var > 0.0f) || !(cfg->kf_rest_r > 0.0f) || dr_fused_kf_start(cfg, st) ||
        !dr_fused_kf_predict(cfg, st)) {
        return;
    }
    dr_fused_rotation(st->q, r);
    for (i = 0; i < 3; i++) {
        h[0][i] = r[0][i];
        h[1][i] = r[1][i];
    }
    if (!dr_fused_kf_update(cfg, st, st->ah[0], st->ah[1], (const float(*)[3])h, cfg->kf_rest_r, x)) {
        return;
    }
    /* the correction leaves the samples from now on: the smoothed value follows */
    st->ah[0] -= x[0] + h[0][0] * x[2] + h[0][1] * x[3] + h[0][2] * x[4];
    st->ah[1] -= x[1] + h[1][0] * x[2] + h[1][1] * x[3] + h[1][2] * x[4];
}

/* The lateral filter stopped (codegen.fused's _nhc_restart): at a fix, at rest, walking: the speed known. It starts
 * again with an outage's next sample of a moving vehicle (dr_fused_nhc_start). */
static void dr_fused_nhc_restart(dr_fused_state *st) {
    int i;
    if (st->nh_u0[0] == 0.0f && st->nh_u0[1] == 0.0f) {
        return; /* not started: all 0 already (u0 is a unit vector once it has) */
    }
    st->nh_t = 0.0f;
    st->nh_z = 0.0f;
    st->nh_r = 0.0f;
    st->nh_b = 0.0f;
    for (i = 0; i < 2; i++) {
        st->nh_f[i] = 0.0f;
        st->nh_u0[i] = 0.0f;
        st->nh_i[i] = 0.0f;
    }
    for (i = 0; i < 10; i++) {
        st->nh_p[i] = 0.0f;
    }
}

/* The lateral filter's start (codegen.fused's _nhc_start): the lateral leak 0 +- nhc_leak_sigma_ms2, the folded
 * offsets 0 with what the tilt/offset filter does not know of the offsets seen horizontally, R_h P_bb R_h^T (times
 * nhc_fold_scale, R_h the horizontal rows of R(q), q the attitude now), and the travel direction they turn from. */
static void dr_fused_nhc_start(const dr_fused_config *cfg, dr_fused_state *st, const float q[4]) {
    float pm[5][5], r[3][3], rp[2][3], c[3] = {0.0f, 0.0f, 0.0f};
    int a, j, k;
    dr_fused_p_load(st, pm);
    dr_fused_rotation(q, r);
    for (a = 0; a < 2; a++) { /* R_h P_bb */
        for (j = 0; j < 3; j++) {
            rp[a][j] = 0.0f;
            for (k = 0; k < 3; k++) {
                rp[a][j] += r[a][k] * pm[2 + k][2 + j];
            }
        }
    }
    for (j = 0; j < 3; j++) { /* (R_h P_bb R_h^T): xx, xy, yy */
        c[0] += rp[0][j] * r[0][j];
        c[1] += rp[0][j] * r[1][j];
        c[2] += rp[1][j] * r[1][j];
    }
    st->nh_p[4] = cfg->nhc_leak_var;
    st->nh_p[7] = cfg->nhc_fold_scale * c[0];
    st->nh_p[8] = cfg->nhc_fold_scale * c[1];
    st->nh_p[9] = cfg->nhc_fold_scale * c[2];
    st->nh_u0[0] = st->ux;
    st->nh_u0[1] = st->uy;
}

/* A vehicle's lateral update in an outage, every nhc_period_s T (codegen.fused's _nhc_update): a 4-state Kalman filter
 * of the speed error e (fed back into the speed), the lateral leak l and the folded offsets f (kernel frame),
 * z = l + (n0 - nbar) . f - rbar e + noise, e grown by T (u0 - ubar) . (f - f_estimated); rbar the mean rate about Up
 * (0 below nhc_min_rate, its speed error term then noise), the noise's variance nhc_var / T. */
static void dr_fused_lateral_feed_back(const dr_fused_config *cfg, dr_fused_state *st, const float x[4]);

static void dr_fused_nhc_update(const dr_fused_config *cfg, dr_fused_state *st) {
    const float t = st->nh_t, inv_t = dr_recip(st->nh_t);
    float rbar = st->nh_r * inv_t, z = st->nh_z * inv_t, turn = cfg->nhc_leak_turn * st->nh_r, unseen = 0.0f;
    float h[4], x[4], dux, duy, y;
    if (dr_absf(rbar) < cfg->nhc_min_rate) {
        unseen = rbar * rbar; /* no turn: a handlebar's or a hand's wobble about Up is no turn of the vehicle */
        rbar = 0.0f;
    }
    dux = st->nh_u0[0] - st->nh_i[0] * inv_t; /* u0 - ubar; n0 - nbar = (-duy, dux) */
    duy = st->nh_u0[1] - st->nh_i[1] * inv_t;
    if (dr_fused_lateral_predict(cfg, st, t * dux, t * duy, cfg->nhc_speed_q * t, turn * turn)) {
        h[0] = -rbar;
        h[1] = 1.0f;
        h[2] = -duy;
        h[3] = dux;
        y = z - st->nh_b - h[2] * st->nh_f[0] - h[3] * st->nh_f[1];
        if (dr_fused_lateral_correct(cfg, st, h, cfg->nhc_var * inv_t + unseen * st->nh_p[0], y, x)) {
            dr_fused_lateral_feed_back(cfg, st, x);
        }
    }
    st->nh_t = 0.0f;
    st->nh_z = 0.0f;
    st->nh_r = 0.0f;
    st->nh_i[0] = 0.0f;
    st->nh_i[1] = 0.0f;
}

/* The lateral filter's predict P <- F P F^T + Q (codegen.fused's _lateral_predict): F = I + A, A only in row 0 (f2, f3
 * in columns 2, 3), so row and column 0 gain (A P)[0], the corner twice that plus A P A^T; Q = diag(q_speed, q_leak,
 * 0, 0). Returns 0 if the covariance went wrong (the filter restarted). */
int dr_fused_lateral_predict(const dr_fused_config *cfg, dr_fused_state *st, float f2, float f3, float q_speed,
                             float q_leak) {
    float *p = st->nh_p; /* upper triangle: 0 ss, 1 sb, 2 sx, 3 sy, 4 bb, 5 bx, 6 by, 7 xx, 8 xy, 9 yy */
    const float ap0 = f2 * p[2] + f3 * p[3]; /* row 0 of A P */
    const float ap1 = f2 * p[5] + f3 * p[6];
    const float ap2 = f2 * p[7] + f3 * p[8];
    const float ap3 = f2 * p[8] + f3 * p[9];
    p[0] += 2.0f * ap0 + (f2 * ap2 + f3 * ap3) + q_speed;
    p[1] += ap1;
    p[2] += ap2;
    p[3] += ap3;
    p[4] += q_leak;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_LATERAL, DR_FUSED_STEP_PREDICT, 1);
}

/* The lateral filter's update with z = h . x + noise (variance r), innovation y (codegen.fused's _lateral_correct):
 * P <- P - K S K^T, K = P h / S. x: the correction K y. Returns 0 if the covariance went wrong (the filter
 * restarted, x unset). */
int dr_fused_lateral_correct(const dr_fused_config *cfg, dr_fused_state *st, const float h[4], float r, float y,
                             float x[4]) {
    float pm[4][4], ph[4], gain[4], s = r, inv_s;
    int i, j, n = 0;
    for (i = 0; i < 4; i++) {
        for (j = i; j < 4; j++) {
            pm[i][j] = st->nh_p[n];
            pm[j][i] = st->nh_p[n];
            n++;
        }
    }
    for (i = 0; i < 4; i++) {
        ph[i] = pm[i][0] * h[0] + pm[i][1] * h[1] + pm[i][2] * h[2] + pm[i][3] * h[3];
    }
    for (i = 0; i < 4; i++) {
        s += h[i] * ph[i];
    }
    if (!(s > 0.0f && s <= DR_FUSED_COV_MAX)) {
        return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_LATERAL, DR_FUSED_STEP_UPDATE, 0);
    }
    inv_s = dr_recip(s);
    for (i = 0; i < 4; i++) {
        gain[i] = ph[i] * inv_s;
    }
    n = 0;
    for (i = 0; i < 4; i++) {
        for (j = i; j < 4; j++) {
            st->nh_p[n++] = pm[i][j] - gain[i] * ph[j];
        }
    }
    if (!dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_LATERAL, DR_FUSED_STEP_UPDATE, 1)) {
        return 0;
    }
    for (i = 0; i < 4; i++) {
        x[i] = gain[i] * y;
    }
    return 1;
}

/* The lateral update's correction x (codegen.fused's _lateral_feed_back): the speed error out of the speed and, as
 * the zero-velocity update takes it, its integral out of the position; the leak and the folded offsets in. */
static void dr_fused_lateral_feed_back(const dr_fused_config *cfg, dr_fused_state *st, const float x[4]) {
    const float e = x[0];
    st->speed -= e;
    st->zr_v -= e;
    if (cfg->nhc_position > 0.0f && st->zr_t > 0.0f) {
        float k = cfg->nhc_position * e * dr_recip(st->zr_t);
        st->pe -= k * st->zr_p[0];
        st->pn -= k * st->zr_p[1];
    }
    if (st->speed < 0.0f) {
        st->speed = 0.0f;
    }
    st->nh_b += x[1];
    st->nh_f[0] += x[2];
    st->nh_f[1] += x[3];
}

int dr_fused_process(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st, const int16_t *samples,
                     const int32_t *dt_us, int32_t count, float out[6]) {
    const float g = DR_GRAVITY_MS2;
    const float db2 = kcfg->deadband_ms2 * kcfg->deadband_ms2;
    const int platform = (int)cfg->platform;
    float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
    float pe0 = st->pe, pn0 = st->pn;
    float ve, vn;
    int32_t k;
    int flags = (int)st->flags;
    int vehicle = platform == DR_FUSED_PLATFORM_VEHICLE || (flags & DR_FUSED_VEHICLE);
    int driven = flags & DR_FUSED_SHAKEN;
    int fast = (flags & DR_FUSED_FAST) && platform != DR_FUSED_PLATFORM_PEDESTRIAN;
    int walked = flags & DR_FUSED_WALKED;
    int32_t median = cfg->median > 0.0f && kcfg->block > 1 ? kcfg->block : 0;
    if (count < 1) {
        return DR_ERR_COUNT;
    }
    if (median > DR_FUSED_MEDIAN_MAX) {
        return DR_ERR_BLOCK;
    }
    for (k = 0; k < count; k++) {
        const int16_t *s = samples + 6 * k;
        float dt = (float)dt_us[k] * DR_S_PER_US;
        float f[3], c[3], w[3];
        float nf, alpha, beta, gamma, d, h, r00, r01, r02, r10, r11, r12, r20, r21, r22, ae, an, de, dn, r, da, ux, uy,
            ue, un, inv, gain, cx, cy, cz, nc2;
        int i, rest, walking, steps, shaken, broadband, still, turning = flags & DR_FUSED_TURNING;
        for (i = 0; i < 3; i++) {
            int32_t src = kcfg->axis_source[i];
            f[i] = kcfg->axis_sign[i] * (float)s[src] * kcfg->accel_ms2_per_lsb;
            c[i] = kcfg->axis_sign[i] * (float)s[3 + src];
            w[i] = (c[i] - st->gyro_bias_lsb[i]) * kcfg->gyro_rads_per_lsb;
        }
        f[0] -= st->bax;
        f[1] -= st->bay;
        f[2] -= st->baz;
        /* motion statistics */
        nf = dr_sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        alpha = dt * cfg->inv_stat_tau;
        if (alpha > 1.0f) {
            alpha = 1.0f;
        }
        st->mean_f += alpha * (nf - st->mean_f);
        d = nf - st->mean_f;
        st->var_f += alpha * (d * d - st->var_f);
        /* the shaking above the gait band: |f| through two first-order high-passes at vibration_hz */
        beta = dt * cfg->vib_rate;
        if (beta > 1.0f) {
            beta = 1.0f;
        }
        st->vib_lp[0] += beta * (nf - st->vib_lp[0]);
        h = nf - st->vib_lp[0];
        st->vib_lp[1] += beta * (h - st->vib_lp[1]);
        h -= st->vib_lp[1];
        gamma = dt * cfg->inv_vib_tau;
        if (gamma > 1.0f) {
            gamma = 1.0f;
        }
        st->vib_var += gamma * (h * h - st->vib_var);
        st->vib_tot += gamma * (d * d - st->vib_tot);
        /* the body rate smoothed: an idling engine's shake averages out */
        for (i = 0; i < 3; i++) {
            st->ws[i] += alpha * (w[i] - st->ws[i]);
        }
        /* rotation matrix of q */
        r00 = 1.0f - 2.0f * (qy * qy + qz * qz);
        r01 = 2.0f * (qx * qy - qw * qz);
        r02 = 2.0f * (qx * qz + qw * qy);
        r10 = 2.0f * (qx * qy + qw * qz);
        r11 = 1.0f - 2.0f * (qx * qx + qz * qz);
        r12 = 2.0f * (qy * qz - qw * qx);
        r20 = 2.0f * (qx * qz - qw * qy);
        r21 = 2.0f * (qy * qz + qw * qx);
        r22 = 1.0f - 2.0f * (qx * qx + qy * qy);
        ae = r00 * f[0] + r01 * f[1] + r02 * f[2];
        an = r10 * f[0] + r11 * f[1] + r12 * f[2];
        shaken = st->var_f > cfg->walk_var;
        broadband = st->vib_var > cfg->vib_ratio * st->vib_tot;
        /* rest: still, a steady horizontal acceleration, no fix saying it moves, and that acceleration within the
         * deadband (a vehicle quiet after shaking, or below rest_speed_ms: any). Still: below rest_accel_g, or below
         * still_accel_g for a pedestrian's hand, idle_accel_g for a vehicle's idling engine (broadband, slower than
         * rest_speed_ms) */
        st->ah[0] += alpha * (ae - st->ah[0]);
        st->ah[1] += alpha * (an - st->ah[1]);
        de = ae - st->ah[0];
        dn = an - st->ah[1];
        still = st->var_f < cfg->rest_var;
        if (!still && vehicle) {
            still = st->var_f < cfg->idle_var && broadband && st->speed < cfg->rest_speed_ms;
        } else if (!still) {
            still = st->var_f < cfg->still_var;
        }
        if (still && st->ws[0] * st->ws[0] + st->ws[1] * st->ws[1] + st->ws[2] * st->ws[2] < cfg->rest_w2 &&
            de * de + dn * dn < db2 &&
            (ae * ae + an * an < db2 || (vehicle && (driven || st->speed < cfg->rest_speed_ms))) &&
            !(st->since_fix < cfg->gps_timeout_s && st->gps_ok > 0.0f)) {
            st->rest_s += dt;
        } else {
            st->rest_s = 0.0f;
        }
        rest = st->rest_s >= cfg->rest_time_s;
        /* walking: shaken, not at rest, in the gait band (auto) for walk_time_s, and nothing says a vehicle (a fast
         * fix since the last rest, its own speed beyond a runner's); a vehicle: shaken above it, a fast fix, or the
         * platform */
        steps = platform != DR_FUSED_PLATFORM_VEHICLE && shaken && !rest &&
                (platform == DR_FUSED_PLATFORM_PEDESTRIAN ||
                 !(broadband || fast || (vehicle && st->speed > cfg->pedestrian_max_ms)));
        st->walk_s = steps ? st->walk_s + dt : 0.0f;
        walking = steps && ((flags & DR_FUSED_WALKING) || st->walk_s >= cfg->walk_time_s);
        if (walking) {
            vehicle = 0;
            walked = DR_FUSED_WALKED;
        } else if (fast || (shaken && broadband && platform != DR_FUSED_PLATFORM_PEDESTRIAN && !walked)) {
            vehicle = 1;
        }
        if (vehicle) {
            walked = 0;
        }
        if (rest) { /* a walker's stop keeps him a pedestrian (walked) */
            driven = 0;
            fast = 0;
        } else if (shaken && vehicle) {
            driven = DR_FUSED_SHAKEN;
        }
        if ((flags & DR_FUSED_WALKING) && !walking) {
            st->speed = 0.0f; /* the steps stopped, and so did the walker */
        }
        /* travel direction turned by the rate about Up; a walker's slow rotations (the hand) held back */
        r = r20 * w[0] + r21 * w[1] + r22 * w[2];
        st->turn += dr_absf(r) * dt;
        st->rate_up += alpha * (r - st->rate_up);
        da = r * dt;
        if (walking && cfg->hold_rate > 0.0f) {
            float hold = dt * cfg->hold_rate;
            if (dr_absf(st->rate_up) > cfg->turn_start) {
                turning = DR_FUSED_TURNING;
            } else if (dr_absf(st->rate_up) < cfg->turn_end) {
                turning = 0;
            }
            st->held += da;
            da = turning ? st->held : st->held * (hold < 1.0f ? hold : 1.0f);
            st->held -= da;
        } else {
            turning = 0;
            da += st->held;
            st->held = 0.0f;
        }
        flags = (rest ? DR_FUSED_AT_REST : 0) | (walking ? DR_FUSED_WALKING : 0) | turning |
                (vehicle ? DR_FUSED_VEHICLE : 0) | driven | (fast ? DR_FUSED_FAST : 0) | walked;
        /* u rotated by da, to second order */
        {
            float cd = 1.0f - 0.5f * da * da, sd = da * (1.0f - da * da * (1.0f / 6.0f));
            ux = cd * st->ux - sd * st->uy;
            uy = cd * st->uy + sd * st->ux;
        }
        inv = dr_inv_sqrt(ux * ux + uy * uy);
        st->ux = ux * inv;
        st->uy = uy * inv;
        /* speed along u */
        if (rest || walking || walked) { /* the median ring restarts when the vehicle branch is entered again */
            st->med_i = 0.0f;
            st->med_n = 0.0f;
            st->acc_lp = 0.0f;
        }
        if (rest) {
            if (st->zr_t > 0.0f) {
                /* a vehicle's zero-velocity update: the speed it still had is the error gathered since its speed
                 * was last known; its integral along the way, and what the floor at 0 kept out, taken back */
                float kz = st->zr_v * dr_recip(st->zr_t);
                st->pe += st->zr_c[0] - kz * st->zr_p[0];
                st->pn += st->zr_c[1] - kz * st->zr_p[1];
            }
            st->speed = 0.0f;
            st->zr_v = 0.0f;
        } else if (walking || walked) {
            /* walking: the learned walking speed; a pedestrian whose steps stopped without a rest: the speed decays
             * to 0 over stand_tau_s, never integrated */
            if (walking) {
                st->speed = st->walk_speed;
            } else {
                float decay = dt * cfg->inv_stand_tau;
                st->speed -= st->speed * (decay < 1.0f ? decay : 1.0f);
            }
            st->zr_v = st->speed;
        } else {
            float a = ae * st->ux + an * st->uy;
            if (median) { /* the seed's block median, sliding: the median of the last b along-track accelerations */
                float window[DR_FUSED_MEDIAN_MAX];
                int32_t slot = (int32_t)st->med_i, filled = (int32_t)st->med_n + 1, m;
                st->med[slot] = a;
                st->med_i = (float)(slot + 1 == median ? 0 : slot + 1);
                if (filled > median) {
                    filled = median;
                }
                st->med_n = (float)filled;
                for (m = 0; m < filled; m++) { /* after a restart the ring fills from slot 0 */
                    window[m] = st->med[m];
                }
                a = dr_median(window, filled);
            }
            /* the folded offsets turned with the vehicle since the outage began: along u they leak (u0 - u) . f */
            a -= st->bias + (st->nh_u0[0] - st->ux) * st->nh_f[0] + (st->nh_u0[1] - st->uy) * st->nh_f[1];
            if (cfg->inv_accel_tau > 0.0f) { /* the deadband gates on the smoothed acceleration (not the road's) */
                float b = dt * cfg->inv_accel_tau;
                st->acc_lp += (b < 1.0f ? b : 1.0f) * (a - st->acc_lp);
                if (dr_absf(st->acc_lp) < kcfg->deadband_ms2) {
                    a = 0.0f;
                }
            } else if (dr_absf(a) < kcfg->deadband_ms2) { /* the board's deadband, on the along-track acceleration */
                a = 0.0f;
            }
            a += (st->gps_speed - st->speed) * cfg->inv_speed_tau;
            st->speed += a * dt;
            st->zr_v += a * dt;
            if (st->speed < 0.0f) {
                st->speed = 0.0f;
            }
        }
        if (rest || walking || walked) {
            st->zr_t = 0.0f;
            st->zr_turn = 0.0f;
            for (i = 0; i < 2; i++) {
                st->zr_p[i] = 0.0f;
                st->zr_c[i] = 0.0f;
            }
        }
        if (cfg->nhc_var > 0.0f) {
            if (rest || walking || !vehicle || st->since_fix < cfg->gps_timeout_s) {
                dr_fused_nhc_restart(st);
            } else {
                /* no sideways sliding: a_lat - s r = leak - (s - s_true) r sees the lateral leak and the speed error */
                if (st->nh_u0[0] == 0.0f && st->nh_u0[1] == 0.0f) {
                    const float q_now[4] = {qw, qx, qy, qz};
                    dr_fused_nhc_start(cfg, st, q_now);
                }
                st->nh_t += dt;
                st->nh_z += (an * st->ux - ae * st->uy - st->speed * r) * dt;
                st->nh_r += r * dt;
                st->nh_i[0] += st->ux * dt;
                st->nh_i[1] += st->uy * dt;
                if (st->nh_t + 0.5f * dt >= cfg->nhc_period_s) { /* half a sample's margin: sums agree */
                    dr_fused_nhc_update(cfg, st);
                }
            }
        }
        if (rest && st->rest_s >= cfg->rest_time_s + cfg->rest_update_s) {
            st->zt += dt; /* a rest update every rest_update_s, after the rest's first (the end of the braking) */
        }
        st->dpx += (st->dvx + 0.5f * ae * dt) * dt;
        st->dpy += (st->dvy + 0.5f * an * dt) * dt;
        st->dvx += ae * dt;
        st->dvy += an * dt;
        st->m[0] += r00 * dt;
        st->m[1] += r01 * dt;
        st->m[2] += r10 * dt;
        st->m[3] += r11 * dt;
        st->m2[0] += r02 * dt;
        st->m2[1] += r12 * dt;
        st->since_fix += dt;
        st->kf_t += dt;
        /* position, true ENU */
        ue = st->cos_t * st->ux - st->sin_t * st->uy;
        un = st->sin_t * st->ux + st->cos_t * st->uy;
        st->pe += st->speed * ue * dt;
        st->pn += st->speed * un * dt;
        if (!(rest || walking || walked)) { /* the integrals a zero-velocity update corrects the position by */
            float lag = (st->zr_v - st->speed) * dt;
            st->zr_turn += dr_absf(r) * dt;
            st->zr_t += (1.0f + st->zr_turn * cfg->zupt_turn_weight) * dt;
            st->zr_p[0] += st->zr_t * ue * dt;
            st->zr_p[1] += st->zr_t * un * dt;
            st->zr_c[0] += lag * ue;
            st->zr_c[1] += lag * un;
        }
        /* tilt correction towards gravity (minus the GPS motion acceleration while fixes arrive) */
        if (st->since_fix < cfg->gps_timeout_s) {
            gain = st->steady > 0.0f ? cfg->kp : 0.0f;
            cx = f[0] - (r00 * st->acc_e + r10 * st->acc_n);
            cy = f[1] - (r01 * st->acc_e + r11 * st->acc_n);
            cz = f[2] - (r02 * st->acc_e + r12 * st->acc_n);
        } else {
            gain = cfg->kp_dark;
            cx = f[0];
            cy = f[1];
            cz = f[2];
        }
        nc2 = cx * cx + cy * cy + cz * cz;
        inv = dr_inv_sqrt(nc2);
        if (nc2 > 0.0f && dr_absf(nc2 * inv - g) < cfg->reject_ms2) {
            inv *= gain;
            w[0] += (cy * r22 - cz * r21) * inv;
            w[1] += (cz * r20 - cx * r22) * inv;
            w[2] += (cx * r21 - cy * r20) * inv;
        }
        /* q <- q (x) [1, omega dt / 2], renormalised */
        {
            float hx = 0.5f * w[0] * dt, hy = 0.5f * w[1] * dt, hz = 0.5f * w[2] * dt;
            float nw = qw - qx * hx - qy * hy - qz * hz;
            float nx = qx + qw * hx + qy * hz - qz * hy;
            float ny = qy + qw * hy - qx * hz + qz * hx;
            float nz = qz + qw * hz + qx * hy - qy * hx;
            inv = dr_inv_sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
            qw = nw * inv;
            qx = nx * inv;
            qy = ny * inv;
            qz = nz * inv;
        }
        if (!rest) {
            st->zt = 0.0f;
        } else if (st->zt >= cfg->rest_update_s) {
            st->q[0] = qw;
            st->q[1] = qx;
            st->q[2] = qy;
            st->q[3] = qz;
            dr_fused_rest_update(kcfg, cfg, st);
            qw = st->q[0];
            qx = st->q[1];
            qy = st->q[2];
            qz = st->q[3];
        }
    }
    st->q[0] = qw;
    st->q[1] = qx;
    st->q[2] = qy;
    st->q[3] = qz;
    st->flags = (float)flags;
    ve = st->speed * (st->cos_t * st->ux - st->sin_t * st->uy);
    vn = st->speed * (st->sin_t * st->ux + st->cos_t * st->uy);
    out[0] = st->pe - pe0;
    out[1] = st->pn - pn0;
    out[2] = 0.0f;
    out[3] = ve;
    out[4] = vn;
    out[5] = 0.0f;
    return DR_OK;
}


/* The GPS-aided update of the tilt/offset filter at a fix (codegen.fused's tilt_and_offset_update): called with its
 * velocity, whether it has a course, and the seconds since the previous fix, before those are replaced. */
static void dr_fused_filter(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, int moving, float t) {
    float h[2][3], x[5];
    float inv_t, gx, gy, z0, z1, norm2;
    if (dr_fused_kf_start(cfg, st) || !dr_fused_kf_predict(cfg, st)) {
        return;
    }
    norm2 = st->align_c * st->align_c + st->align_s * st->align_s;
    if (!(st->gps_ok > 0.0f && moving && t > 0.0f && t < cfg->gps_timeout_s &&
          norm2 >= cfg->kf_align_min * cfg->kf_align_min)) {
        return;
    }
    inv_t = dr_recip(t);
    gx = ve - st->gps_ve;
    gy = vn - st->gps_vn;
    z0 = (st->dvx - (st->cos_t * gx + st->sin_t * gy)) * inv_t;
    z1 = (st->dvy - (-st->sin_t * gx + st->cos_t * gy)) * inv_t;
    h[0][0] = st->m[0] * inv_t;
    h[0][1] = st->m[1] * inv_t;
    h[0][2] = st->m2[0] * inv_t;
    h[1][0] = st->m[2] * inv_t;
    h[1][1] = st->m[3] * inv_t;
    h[1][2] = st->m2[1] * inv_t;
    dr_fused_kf_update(cfg, st, z0, z1, (const float(*)[3])h, cfg->kf_vel_r * inv_t * inv_t, x);
}

void dr_fused_position(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, float de, float dn) {
    const float t = st->since_fix;
    float phi, cx, cy, ae, an, ee, en, gain[2];
    if (!(cfg->pos_var > 0.0f)) {
        return;
    }
    if (!(st->fix_pxx > 0.0f && t > 0.0f && t < cfg->gps_timeout_s)) { /* (re)start at the fix itself */
        dr_fused_position_prior(cfg, st);
        dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_POSITION, DR_FUSED_STEP_START, 1);
        return;
    }
    if (!dr_fused_position_predict(cfg, st, t, &phi)) {
        return;
    }
    /* the IMU's correction to the trapezoid T (v0 + v1) / 2, rotated into true ENU below */
    cx = st->dpx - 0.5f * t * st->dvx;
    cy = st->dpy - 0.5f * t * st->dvy;
    ae = st->fix_ae + 0.5f * t * (st->gps_ve + ve) + (st->cos_t * cx - st->sin_t * cy) - de;
    an = st->fix_an + 0.5f * t * (st->gps_vn + vn) + (st->sin_t * cx + st->cos_t * cy) - dn;
    ee = phi * st->fix_ee;
    en = phi * st->fix_en;
    if (!dr_fused_position_correct(cfg, st, gain)) {
        return;
    }
    st->fix_ae = ae - gain[0] * (ae + ee);
    st->fix_an = an - gain[0] * (an + en);
    st->fix_ee = ee - gain[1] * (ae + ee);
    st->fix_en = en - gain[1] * (an + en);
}

/* The position filter (re)started at the fix itself (codegen.fused's _position_prior). */
static void dr_fused_position_prior(const dr_fused_config *cfg, dr_fused_state *st) {
    st->fix_ae = 0.0f;
    st->fix_an = 0.0f;
    st->fix_ee = 0.0f;
    st->fix_en = 0.0f;
    st->fix_pxx = cfg->pos_var;
    st->fix_pee = cfg->pos_var;
    st->fix_pxe = -cfg->pos_var;
}

/* The position filter's predict over t s (codegen.fused's _position_predict): P <- F P F^T + Q, F = diag(1, phi),
 * Q = diag(pos_step_q t^2, pos_var (1 - phi^2)). *phi: exp(-t / pos_tau_s). Returns 0 if the covariance went wrong
 * (restarted at the fix). */
int dr_fused_position_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float *phi) {
    const float x = t * cfg->inv_pos_tau;
    const float f = 1.0f - x * (1.0f - x * (0.5f - x * (1.0f / 6.0f))); /* cubic Taylor (x <= gps_timeout / tau) */
    st->fix_pxx += cfg->pos_step_q * t * t;
    st->fix_pxe *= f;
    st->fix_pee = f * f * st->fix_pee + cfg->pos_var * (1.0f - f * f);
    *phi = f;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_POSITION, DR_FUSED_STEP_PREDICT, 1);
}

/* The position filter's update with the fix y = x + e, H = [1, 1], no noise of its own (codegen.fused's
 * _position_correct): P <- P - K S K^T. gain: K. Returns 0 if the covariance went wrong (restarted at the fix). */
int dr_fused_position_correct(const dr_fused_config *cfg, dr_fused_state *st, float gain[2]) {
    const float pxx = st->fix_pxx, pxe = st->fix_pxe, pee = st->fix_pee;
    const float s = pxx + 2.0f * pxe + pee;
    float inv_s;
    if (!(s > 0.0f && s <= DR_FUSED_COV_MAX)) {
        return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_POSITION, DR_FUSED_STEP_UPDATE, 0);
    }
    inv_s = dr_recip(s);
    gain[0] = (pxx + pxe) * inv_s;
    gain[1] = (pxe + pee) * inv_s;
    st->fix_pxx = pxx - gain[0] * gain[0] * s;
    st->fix_pxe = pxe - gain[0] * gain[1] * s;
    st->fix_pee = pee - gain[1] * gain[1] * s;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_POSITION, DR_FUSED_STEP_UPDATE, 1);
}

void dr_fused_gps(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn) {
    float s2 = ve * ve + vn * vn;
    float inv_speed = dr_inv_sqrt(s2);
    float speed = s2 * inv_speed;
    float t = st->since_fix;
    int moving = speed >= cfg->min_speed_ms;
    int flags = (int)st->flags;
    int i;
    float ae = 0.0f, an = 0.0f, de, dn, e;
    if (st->gps_ok > 0.0f && moving && t > 0.0f && t < cfg->gps_timeout_s) {
        /* heading alignment from the velocity changes */
        float gx = ve - st->gps_ve, gy = vn - st->gps_vn, inv_t, me, mn, norm;
        st->align_c = cfg->align_forget * st->align_c + st->dvx * gx + st->dvy * gy;
        st->align_s = cfg->align_forget * st->align_s + st->dvx * gy - st->dvy * gx;
        norm = dr_inv_sqrt(st->align_c * st->align_c + st->align_s * st->align_s);
        if (norm > 0.0f) { /* the frame turns; the travel direction keeps its true bearing: u <- A'^T A u */
            float ue = st->cos_t * st->ux - st->sin_t * st->uy, un = st->sin_t * st->ux + st->cos_t * st->uy;
            st->cos_t = st->align_c * norm;
            st->sin_t = st->align_s * norm;
            st->ux = st->cos_t * ue + st->sin_t * un;
            st->uy = -st->sin_t * ue + st->cos_t * un;
        }
        /* the motion acceleration over the interval, into the kernel frame */
        inv_t = dr_recip(t);
        me = gx * inv_t;
        mn = gy * inv_t;
        ae = st->cos_t * me + st->sin_t * mn;
        an = -st->sin_t * me + st->cos_t * mn;
    }
    if (cfg->kf_bias_var > 0.0f) {
        dr_fused_filter(cfg, st, ve, vn, moving, t);
    }
    de = ae - st->acc_e;
    dn = an - st->acc_n;
    /* flags kept as margins (> 0 means yes): LLVM's Xtensa backend cannot select a constant pair (x ? 1.0f : 0.0f) */
    st->steady = cfg->steady_ms2 * cfg->steady_ms2 - (de * de + dn * dn);
    st->acc_e = ae;
    st->acc_n = an;
    if (moving) {
        float gx = (st->cos_t * ve + st->sin_t * vn) * inv_speed;
        float gy = (-st->sin_t * ve + st->cos_t * vn) * inv_speed;
        /* before the frame's first alignment u means nothing yet: it takes the course at once */
        float pull = st->align_c != 0.0f || st->align_s != 0.0f ? cfg->heading_gain : 1.0f;
        float ux = st->ux + pull * (gx - st->ux);
        float uy = st->uy + pull * (gy - st->uy);
        float norm = dr_inv_sqrt(ux * ux + uy * uy);
        if (norm > 0.0f) {
            st->ux = ux * norm;
            st->uy = uy * norm;
        }
        if (flags & DR_FUSED_WALKING) { /* what people walk and run: a pedestrian's speed is bounded */
            float bounded = speed < cfg->pedestrian_max_ms ? speed : cfg->pedestrian_max_ms;
            st->walk_speed += cfg->walk_speed_gain * (bounded - st->walk_speed);
        }
    }
    e = speed - st->speed;
    st->speed += cfg->speed_gain * e;
    if (t > 0.0f && !(flags & (DR_FUSED_AT_REST | DR_FUSED_WALKING))) {
        st->bias -= cfg->bias_gain * e * dr_recip(t);
    }
    st->gps_ve = ve;
    st->gps_vn = vn;
    st->gps_speed = speed;
    st->gps_ok = speed - cfg->min_speed_ms;
    if (speed > cfg->pedestrian_max_ms) { /* faster than people run: a vehicle until it rests */
        st->flags = (float)((int)st->flags | DR_FUSED_FAST);
    }
    st->dvx = 0.0f;
    st->dvy = 0.0f;
    st->dpx = 0.0f;
    st->dpy = 0.0f;
    for (i = 0; i < 4; i++) {
        st->m[i] = 0.0f;
    }
    for (i = 0; i < 2; i++) {
        st->m2[i] = 0.0f;
        st->zr_p[i] = 0.0f;
        st->zr_c[i] = 0.0f;
    }
    st->turn = 0.0f;
    st->zr_t = 0.0f;
    st->zr_turn = 0.0f;
    st->zr_v = st->speed;
    st->since_fix = 0.0f;
    dr_fused_nhc_restart(st);
}
