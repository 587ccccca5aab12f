/*
 * dr_fused.c: the fused real-time algorithm; see dr_fused.h and codegen/kernel/fused.py (the specification).
 */
#include "dr_fused.h"

#include "dr_board.h"
#include "dr_math.h"
#include "dr_median.h"

#define DR_FUSED_SUM_CHUNK (1024) /* samples summed in int32 before moving to float (1024 * 32768 < 2^31) */
#define DR_FUSED_COV_MAX (1.0e30f) /* a covariance entry beyond this in magnitude (or not a number) is broken */
#define DR_FUSED_SPEED_UNKNOWN_VAR (1.0e4f) /* (m/s)^2: the speed's variance after a calibration that moved */

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

/* Returns |mean accelerometer counts| of count >= 1 samples (sensor frame: the remap does not change a length),
 * summed in int32 chunks of DR_FUSED_SUM_CHUNK as the fallback sums them. */
static float dr_fused_mean_force_counts(const int16_t *samples, int32_t count) {
    float total[3];
    float inv_count, m2;
    int i;
    for (i = 0; i < 3; i++) {
        total[i] = 0.0f;
    }
    dr_sum_counts(samples, count, 3, DR_FUSED_SUM_CHUNK, total);
    inv_count = dr_recip((float)count);
    m2 = 0.0f;
    for (i = 0; i < 3; i++) {
        float m = total[i] * inv_count;
        m2 += m * m;
    }
    return dr_sqrt(m2);
}

/* The motion statistics started at rest, from the mean specific force st->mean_f (m/s^2): no variance, no
 * vibration, no walking steps, no rest time, speed 0, no along-track offsets. */
static void dr_fused_motion_start(dr_fused_state *st) {
    int i;
    st->var_f = 0.0f;
    st->vib_var = 0.0f;
    st->vib_tot = 0.0f;
    st->vib_lp[DR_FUSED_VIB_LP1] = st->mean_f;
    st->vib_lp[DR_FUSED_VIB_LP2] = 0.0f;
    for (i = 0; i < 3; i++) {
        st->ws[i] = 0.0f;
    }
    st->rest_s = 0.0f;
    st->speed = 0.0f;
    st->bax = 0.0f;
    st->bay = 0.0f;
    st->baz = 0.0f;
}

/* The speed/bias filter's start after a calibration with the verdict code (DR_OK or DR_MOVED): the speed 0 if the
 * device stood still; after a calibration that moved not known, and the gyro bias took the motion's mean rate (the
 * tilt drifts until a rest). */
static void dr_fused_speed_start(dr_fused_state *st, int code) {
    st->sb_p[DR_FUSED_SB_PSS] = 0.0f;
    st->sb_p[DR_FUSED_SB_PSB] = 0.0f;
    st->sb_p[DR_FUSED_SB_PBB] = 0.0f;
    st->sk_t = 0.0f;
    st->keep_v = -1.0f;
    st->cal_moved = 0.0f;
    if (code == DR_MOVED) { /* not a constant pair (x ? a : b): LLVM's Xtensa backend cannot select one */
        st->sb_p[DR_FUSED_SB_PSS] = DR_FUSED_SPEED_UNKNOWN_VAR;
        st->cal_moved = 1.0f;
    }
}

int dr_fused_calibrate(const dr_config *kcfg, dr_fused_state *st, const int16_t *samples, int32_t count) {
    dr_state seed;
    int i, code;
    dr_state_init(&seed);
    code = dr_calibrate(kcfg, &seed, samples, count); /* the tilt and the gyro bias, as the seed kernel's */
    if (code < 0) {
        return code;
    }
    for (i = 0; i < 4; i++) {
        st->q[i] = seed.q[i];
    }
    for (i = 0; i < 3; i++) {
        st->gyro_bias_lsb[i] = seed.gyro_bias_lsb[i];
    }
    st->mean_f = dr_fused_mean_force_counts(samples, count) * kcfg->accel_ms2_per_lsb;
    dr_fused_motion_start(st);
    dr_fused_speed_start(st, code);
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

/* The tilt/offset filter's covariance at its start (codegen.fused's _kf_prior): b ~ kf_bias_init_g per axis across
 * gravity (0 along it), d = -R_h b, from the attitude st->q. */
static void dr_fused_kf_prior(const dr_fused_config *cfg, dr_fused_state *st) {
    float r[3][3], pm[5][5];
    const float v = cfg->kf_bias_var;
    int i, j, c;
    dr_quat_to_matrix(st->q, r);
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
static void dr_fused_speed_prior(const dr_fused_config *cfg, dr_fused_state *st);

/* After a step of a filter (codegen.fused's _covariance_checked): 1 if its covariance is usable (and, for an update,
 * innovation_ok: the innovation's covariance was positive definite); otherwise it is reset to its prior, counted in
 * st->cov_repairs, and 0 returned (the caller uses nothing of the step). */
static int dr_fused_covariance_checked(const dr_fused_config *cfg, dr_fused_state *st, int filter, int step,
                                       int innovation_ok) {
    int usable;
    /* two-way choices only: a chain of four compiles to a jump table in .rodata, which a natmod cannot relocate */
    const int tilt_or_lateral = filter == DR_FUSED_FILTER_TILT || filter == DR_FUSED_FILTER_LATERAL;
    DR_FUSED_OBSERVE(st, filter, step);
    if (!innovation_ok) {
        usable = 0;
    } else if (tilt_or_lateral) {
        if (filter == DR_FUSED_FILTER_TILT) {
            usable = dr_fused_triangle_usable(st->p, 4) && dr_fused_bounded(st->pz[DR_FUSED_P04]) &&
                     dr_fused_bounded(st->pz[DR_FUSED_P14]) && dr_fused_bounded(st->pz[DR_FUSED_P24]) &&
                     dr_fused_bounded(st->pz[DR_FUSED_P34]) && dr_fused_triangle_usable(st->pz + DR_FUSED_P44, 1);
        } else {
            usable = dr_fused_triangle_usable(st->nh_p, 4);
        }
    } else if (filter == DR_FUSED_FILTER_SPEED) {
        usable = dr_fused_triangle_usable(st->sb_p, 2);
    } else {
        usable = dr_fused_bounded(st->fix_pxx) && st->fix_pxx >= 0.0f && dr_fused_bounded(st->fix_pxe) &&
                 dr_fused_bounded(st->fix_pee) && st->fix_pee >= 0.0f;
    }
    if (usable) {
        return 1;
    }
    st->cov_repairs += 1.0f;
    if (tilt_or_lateral) {
        if (filter == DR_FUSED_FILTER_TILT) {
            dr_fused_kf_prior(cfg, st);
        } else {
            dr_fused_nhc_restart(st);
        }
    } else if (filter == DR_FUSED_FILTER_SPEED) {
        st->sb_p[DR_FUSED_SB_PSS] = DR_FUSED_SPEED_UNKNOWN_VAR; /* the speed not known: the next fix restarts it */
        dr_fused_speed_prior(cfg, st);
    } else {
        dr_fused_position_prior(cfg, st);
    }
    return 0;
}

/* Starts the tilt/offset filter on its first use after calibration (codegen.fused's _kf_start). Returns 1 if it
 * started now (no update this time). */
static int dr_fused_kf_start(const dr_fused_config *cfg, dr_fused_state *st) {
    if (st->p[DR_FUSED_P22] > 0.0f) {
        return 0;
    }
    dr_fused_kf_prior(cfg, st);
    dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_START, 1);
    return 1;
}

void dr_fused_keep(const dr_fused_state *st, float kept[DR_FUSED_KEPT_LEN]) {
    const float *s = (const float *)st;
#define DR_FUSED_KEEP_ONE(i, at) kept[i] = s[at];
    DR_FUSED_KEPT(DR_FUSED_KEEP_ONE)
#undef DR_FUSED_KEEP_ONE
}

void dr_fused_restore(const dr_fused_config *cfg, dr_fused_state *st, const float kept[DR_FUSED_KEPT_LEN]) {
    float *s = (float *)st;
    float r[3][3];
    const float v = cfg->kf_bias_var;
#define DR_FUSED_RESTORE_ONE(i, at) s[at] = kept[i];
    DR_FUSED_KEPT(DR_FUSED_RESTORE_ONE)
#undef DR_FUSED_RESTORE_ONE
    st->cal_moved = 0.0f;
    if (st->p[DR_FUSED_P22] > 0.0f) { /* else the filter had not started: it starts at its first use */
        /* the leak's block as the prior's (var R_h R_h^T), its rows against the offsets 0 */
        dr_quat_to_matrix(st->q, r);
        st->p[DR_FUSED_P00] = v * (r[0][0] * r[0][0] + r[0][1] * r[0][1] + r[0][2] * r[0][2]);
        st->p[DR_FUSED_P01] = v * (r[0][0] * r[1][0] + r[0][1] * r[1][1] + r[0][2] * r[1][2]);
        st->p[DR_FUSED_P11] = v * (r[1][0] * r[1][0] + r[1][1] * r[1][1] + r[1][2] * r[1][2]);
        st->p[DR_FUSED_P02] = st->p[DR_FUSED_P03] = st->p[DR_FUSED_P12] = st->p[DR_FUSED_P13] = 0.0f;
        st->pz[DR_FUSED_P04] = st->pz[DR_FUSED_P14] = 0.0f;
        st->kf_t = 0.0f;
        st->turn = 0.0f;
        (void)dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_START, 1);
    }
    (void)dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_SPEED, DR_FUSED_STEP_START, 1);
}

/* The filter's predict P <- P + Q, Q the process noise over the kf_t seconds since its last prediction
 * (codegen.fused's _kf_predict). Returns 0 if the covariance went wrong (reset to the prior). */
int dr_fused_kf_predict(const dr_fused_config *cfg, dr_fused_state *st) {
    float qd = cfg->kf_tilt_q * st->kf_t + cfg->kf_turn_q * st->turn * st->turn;
    float qb = cfg->kf_bias_q * st->kf_t;
    st->p[DR_FUSED_P00] += qd;
    st->p[DR_FUSED_P11] += qd;
    st->p[DR_FUSED_P22] += qb;
    st->p[DR_FUSED_P33] += qb;
    st->pz[DR_FUSED_P44] += qb;
    st->kf_t = 0.0f;
    st->turn = 0.0f;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_TILT, DR_FUSED_STEP_PREDICT, 1);
}

/* The tilt/offset filter's correction x fed back (codegen.fused's _kf_update): b into bax, bay, baz, d as a small
 * rotation of q about the kernel frame's horizontal axes. */
static inline void dr_fused_kf_feed_back(dr_fused_state *st, const float x[5]) {
    float hx, hy;
    st->bax += x[2];
    st->bay += x[3];
    st->baz += x[4];
    /* remove the leak: q <- [1, (d_N / g, -d_E / g, 0) / 2] (x) q */
    hx = 0.5f * x[1] * DR_INV_GRAVITY;
    hy = -0.5f * x[0] * DR_INV_GRAVITY;
    {
        float qw = st->q[DR_FUSED_QW], qx = st->q[DR_FUSED_QX], qy = st->q[DR_FUSED_QY], qz = st->q[DR_FUSED_QZ];
        float nw = qw - hx * qx - hy * qy;
        float nx = qx + hx * qw + hy * qz;
        float ny = qy + hy * qw - hx * qz;
        float nz = qz + hx * qy - hy * qx;
        float inv = dr_inv_sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
        st->q[DR_FUSED_QW] = nw * inv;
        st->q[DR_FUSED_QX] = nx * inv;
        st->q[DR_FUSED_QY] = ny * inv;
        st->q[DR_FUSED_QZ] = nz * inv;
    }
}

/* The filter's update with z = d + h b + noise (variance r per axis), H = [I2 | h]: P <- P - K S K^T, fed back at
 * once (codegen.fused's _kf_update): b into bax, bay, baz, d as a small rotation of q about the kernel frame's
 * horizontal axes. x: the correction. Returns 0 if the covariance went wrong (reset to the prior, nothing fed back,
 * x unset). */
/* The filter's P H^T and innovation covariance S = H P H^T + r I (s: s00, s01, s11) for z = d + h b + noise,
 * H = [I2 | h] (codegen.fused's _kf_innovation). */
static void dr_fused_kf_innovation(const float pm[5][5], const float h[2][3], float r, float pht[5][2], float s[3]) {
    int i, j, c;
    for (i = 0; i < 5; i++) {
        for (j = 0; j < 2; j++) {
            pht[i][j] = pm[i][j];
            for (c = 0; c < 3; c++) {
                pht[i][j] += pm[i][2 + c] * h[j][c];
            }
        }
    }
    s[0] = pht[0][0] + r;
    s[1] = pht[0][1];
    s[2] = pht[1][1] + r;
    for (c = 0; c < 3; c++) {
        s[0] += h[0][c] * pht[2 + c][0];
        s[1] += h[0][c] * pht[2 + c][1];
        s[2] += h[1][c] * pht[2 + c][1];
    }
}

int dr_fused_kf_update(const dr_fused_config *cfg, dr_fused_state *st, float z0, float z1, const float h[2][3],
                       float r, float x[5]) {
    float pm[5][5], pht[5][2], gain[5][2], sv[3];
    float s00, s01, s11, inv_det, i00, i01, i11;
    int i, j;
    dr_fused_p_load(st, pm);
    dr_fused_kf_innovation((const float(*)[5])pm, h, r, pht, sv);
    s00 = sv[0];
    s01 = sv[1];
    s11 = sv[2];
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
    dr_fused_kf_feed_back(st, x);
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
    dr_quat_to_matrix(st->q, r);
    for (i = 0; i < 3; i++) {
        h[0][i] = r[0][i];
        h[1][i] = r[1][i];
    }
    if (!dr_fused_kf_update(cfg, st, st->ah[DR_FUSED_AH_E], st->ah[DR_FUSED_AH_N], (const float(*)[3])h,
                            cfg->kf_rest_r, x)) {
        return;
    }
    /* the correction leaves the samples from now on: the smoothed value follows */
    st->ah[DR_FUSED_AH_E] -= x[0] + h[0][0] * x[2] + h[0][1] * x[3] + h[0][2] * x[4];
    st->ah[DR_FUSED_AH_N] -= x[1] + h[1][0] * x[2] + h[1][1] * x[3] + h[1][2] * x[4];
}

/* The lateral filter stopped (codegen.fused's _nhc_restart): at a fix, at rest, walking: the speed known. It starts
 * again with an outage's next sample of a moving vehicle (dr_fused_nhc_start). */
static void dr_fused_nhc_restart(dr_fused_state *st) {
    int i;
    if (st->nh_u0[DR_FUSED_NH_U0X] == 0.0f && st->nh_u0[DR_FUSED_NH_U0Y] == 0.0f) {
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
    dr_quat_to_matrix(q, r);
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
    st->nh_p[DR_FUSED_NH_PBB] = cfg->nhc_leak_var;
    st->nh_p[DR_FUSED_NH_PXX] = cfg->nhc_fold_scale * c[0];
    st->nh_p[DR_FUSED_NH_PXY] = cfg->nhc_fold_scale * c[1];
    st->nh_p[DR_FUSED_NH_PYY] = cfg->nhc_fold_scale * c[2];
    st->nh_u0[DR_FUSED_NH_U0X] = st->ux;
    st->nh_u0[DR_FUSED_NH_U0Y] = st->uy;
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
    dux = st->nh_u0[DR_FUSED_NH_U0X] - st->nh_i[DR_FUSED_NH_IX] * inv_t; /* u0 - ubar; n0 - nbar = (-duy, dux) */
    duy = st->nh_u0[DR_FUSED_NH_U0Y] - st->nh_i[DR_FUSED_NH_IY] * inv_t;
    if (dr_fused_lateral_predict(cfg, st, t * dux, t * duy, cfg->nhc_speed_q * t, turn * turn)) {
        h[0] = -rbar;
        h[1] = 1.0f;
        h[2] = -duy;
        h[3] = dux;
        y = z - st->nh_b - h[2] * st->nh_f[DR_FUSED_NH_FX] - h[3] * st->nh_f[DR_FUSED_NH_FY];
        if (dr_fused_lateral_correct(cfg, st, h, cfg->nhc_var * inv_t + unseen * st->nh_p[DR_FUSED_NH_PSS], y, x)) {
            dr_fused_lateral_feed_back(cfg, st, x);
        }
    }
    st->nh_t = 0.0f;
    st->nh_z = 0.0f;
    st->nh_r = 0.0f;
    st->nh_i[DR_FUSED_NH_IX] = 0.0f;
    st->nh_i[DR_FUSED_NH_IY] = 0.0f;
}

/* The lateral filter's predict P <- F P F^T + Q (codegen.fused's _lateral_predict): F = I + A, A only in row 0 (f2, f3
 * in columns 2, 3), so row and column 0 gain (A P)[0], the corner twice that plus A P A^T; Q = diag(q_speed, q_leak,
 * 0, 0). Returns 0 if the covariance went wrong (the filter restarted). */
int dr_fused_lateral_predict(const dr_fused_config *cfg, dr_fused_state *st, float f2, float f3, float q_speed,
                             float q_leak) {
    float *p = st->nh_p; /* the upper triangle, row by row: speed error s, leak b, folded offsets x, y */
    const float ap0 = f2 * p[DR_FUSED_NH_PSX] + f3 * p[DR_FUSED_NH_PSY]; /* row 0 of A P */
    const float ap1 = f2 * p[DR_FUSED_NH_PBX] + f3 * p[DR_FUSED_NH_PBY];
    const float ap2 = f2 * p[DR_FUSED_NH_PXX] + f3 * p[DR_FUSED_NH_PXY];
    const float ap3 = f2 * p[DR_FUSED_NH_PXY] + f3 * p[DR_FUSED_NH_PYY];
    p[DR_FUSED_NH_PSS] += 2.0f * ap0 + (f2 * ap2 + f3 * ap3) + q_speed;
    p[DR_FUSED_NH_PSB] += ap1;
    p[DR_FUSED_NH_PSX] += ap2;
    p[DR_FUSED_NH_PSY] += ap3;
    p[DR_FUSED_NH_PBB] += q_leak;
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
        st->pe -= k * st->zr_p[DR_FUSED_ZR_PE];
        st->pn -= k * st->zr_p[DR_FUSED_ZR_PN];
    }
    if (st->speed < 0.0f) {
        st->speed = 0.0f;
    }
    st->nh_b += x[1];
    st->nh_f[DR_FUSED_NH_FX] += x[2];
    st->nh_f[DR_FUSED_NH_FY] += x[3];
}

/* ---- the per-sample loop, as named steps in the order dr_fused_process calls them (docs/fused.md "Per sample";
 * codegen/kernel/fused.py's _<step> and the fallback's blocks labelled `step: <step>` are the same steps) ---- */

/* What the per-sample steps share within one dr_fused_process call: the attitude and the platform's decisions
 * carried from sample to sample, and the current sample's values (the compiler keeps them in registers). */
typedef struct {
    /* carried between samples */
    float q[4];   /* the attitude w, x, y, z (stored into st at a rest update and at the end) */
    int flags;    /* the last sample's flags (DR_FUSED_*) */
    int vehicle;  /* the platform's decisions: a vehicle, shaken since its last rest (DR_FUSED_SHAKEN), a fast fix */
    int driven;
    int fast;
    int walked;   /* DR_FUSED_WALKED or 0 */
    int drove;    /* DR_FUSED_DROVE or 0 */
    int platform; /* DR_FUSED_PLATFORM_* */
    int32_t median; /* the median option's b, or 0 */
    float db2;    /* (m/s^2)^2: the kernel's deadband squared */
    /* this sample */
    float dt;     /* s */
    float fx, fy, fz; /* m/s^2: specific force, body frame, less the offsets */
    float wx, wy, wz; /* rad/s: rate, body frame, less the gyro bias */
    float nf;     /* m/s^2: |f| */
    float d;      /* m/s^2: |f| less its mean */
    float alpha;  /* the motion statistics' step, dt / stat_tau_s (at most 1) */
    float r00, r01, r02, r10, r11, r12, r20, r21, r22; /* R(q): body -> kernel ENU */
    float ae, an; /* m/s^2: the horizontal specific force, kernel frame */
    float r;      /* rad/s: the rate about Up */
    int shaken, broadband, rest, walking, turning;
    float sp;     /* m/s: the speed the position moves by (a vehicle's weighed against the one it keeps) */
} dr_fused_loop;

/* The sample in the body frame (codegen.fused's _sample_in): the remap and scales, the accelerometer's offsets and
 * the gyro bias taken out. */
static inline void dr_fused_sample_in(const dr_config *kcfg, const dr_fused_state *st, dr_fused_loop *lp,
                                      const int16_t *s, int32_t dt_us) {
    const int32_t sx = kcfg->axis_source[0], sy = kcfg->axis_source[1], sz = kcfg->axis_source[2];
    const float kx = kcfg->axis_sign[0], ky = kcfg->axis_sign[1], kz = kcfg->axis_sign[2];
    float cx, cy, cz;
    lp->dt = (float)dt_us * DR_S_PER_US;
    lp->fx = kx * (float)s[sx] * kcfg->accel_ms2_per_lsb;
    lp->fy = ky * (float)s[sy] * kcfg->accel_ms2_per_lsb;
    lp->fz = kz * (float)s[sz] * kcfg->accel_ms2_per_lsb;
    lp->fx -= st->bax; /* a statement of its own, as before: no compiler contracts it into the product */
    lp->fy -= st->bay;
    lp->fz -= st->baz;
    cx = kx * (float)s[3 + sx]; /* counts */
    cy = ky * (float)s[3 + sy];
    cz = kz * (float)s[3 + sz];
    lp->wx = (cx - st->gyro_bias_lsb[DR_FUSED_BGX]) * kcfg->gyro_rads_per_lsb;
    lp->wy = (cy - st->gyro_bias_lsb[DR_FUSED_BGY]) * kcfg->gyro_rads_per_lsb;
    lp->wz = (cz - st->gyro_bias_lsb[DR_FUSED_BGZ]) * kcfg->gyro_rads_per_lsb;
}

/* The mean and variance of |f| over stat_tau_s, its shaking above the gait band (two first-order high-passes at
 * vibration_hz) and the variance that is a share of, over vibration_tau_s, the body rate smoothed (an idling
 * engine's shake averages out); shaken (beyond walk_accel_g) and broadband (codegen.fused's _motion_statistics). */
static inline void dr_fused_motion_statistics(const dr_fused_config *cfg, dr_fused_state *st, dr_fused_loop *lp) {
    const float dt = lp->dt;
    float nf, alpha, beta, gamma, d, h;
    nf = dr_sqrt(lp->fx * lp->fx + lp->fy * lp->fy + lp->fz * lp->fz);
    alpha = dt * cfg->inv_stat_tau;
    if (alpha > 1.0f) {
        alpha = 1.0f;
    }
    st->mean_f += alpha * (nf - st->mean_f);
    d = nf - st->mean_f;
    st->var_f += alpha * (d * d - st->var_f);
    beta = dt * cfg->vib_rate;
    if (beta > 1.0f) {
        beta = 1.0f;
    }
    st->vib_lp[DR_FUSED_VIB_LP1] += beta * (nf - st->vib_lp[DR_FUSED_VIB_LP1]);
    h = nf - st->vib_lp[DR_FUSED_VIB_LP1];
    st->vib_lp[DR_FUSED_VIB_LP2] += beta * (h - st->vib_lp[DR_FUSED_VIB_LP2]);
    h -= st->vib_lp[DR_FUSED_VIB_LP2];
    gamma = dt * cfg->inv_vib_tau;
    if (gamma > 1.0f) {
        gamma = 1.0f;
    }
    st->vib_var += gamma * (h * h - st->vib_var);
    st->vib_tot += gamma * (d * d - st->vib_tot);
    st->ws[DR_FUSED_WSX] += alpha * (lp->wx - st->ws[DR_FUSED_WSX]);
    st->ws[DR_FUSED_WSY] += alpha * (lp->wy - st->ws[DR_FUSED_WSY]);
    st->ws[DR_FUSED_WSZ] += alpha * (lp->wz - st->ws[DR_FUSED_WSZ]);
    lp->nf = nf;
    lp->d = d;
    lp->alpha = alpha;
    lp->shaken = st->var_f > cfg->walk_var;
    lp->broadband = st->vib_var > cfg->vib_ratio * st->vib_tot;
}

/* R(q)'s rows and the horizontal specific force in the kernel frame, smoothed over stat_tau_s (rest: steady)
 * (codegen.fused's _horizontal_force). */
static inline void dr_fused_horizontal_force(dr_fused_state *st, dr_fused_loop *lp) {
    const float qw = lp->q[0], qx = lp->q[1], qy = lp->q[2], qz = lp->q[3];
    lp->r00 = 1.0f - 2.0f * (qy * qy + qz * qz);
    lp->r01 = 2.0f * (qx * qy - qw * qz);
    lp->r02 = 2.0f * (qx * qz + qw * qy);
    lp->r10 = 2.0f * (qx * qy + qw * qz);
    lp->r11 = 1.0f - 2.0f * (qx * qx + qz * qz);
    lp->r12 = 2.0f * (qy * qz - qw * qx);
    lp->r20 = 2.0f * (qx * qz - qw * qy);
    lp->r21 = 2.0f * (qy * qz + qw * qx);
    lp->r22 = 1.0f - 2.0f * (qx * qx + qy * qy);
    lp->ae = lp->r00 * lp->fx + lp->r01 * lp->fy + lp->r02 * lp->fz;
    lp->an = lp->r10 * lp->fx + lp->r11 * lp->fy + lp->r12 * lp->fz;
    st->ah[DR_FUSED_AH_E] += lp->alpha * (lp->ae - st->ah[DR_FUSED_AH_E]);
    st->ah[DR_FUSED_AH_N] += lp->alpha * (lp->an - st->ah[DR_FUSED_AH_N]);
}

/* Can the tilt/offset filter take a quiet vehicle's steady horizontal specific force for its own error, as the rest
 * update would (codegen.fused's _rest_explained)? Its normalised square below rest_gate, S with the predict due
 * since the filter's last one counted, not stored: a smooth start from a stand is no rest. Before the filter's
 * start (or with rest_gate 0): any force. */
static int dr_fused_rest_explained(const dr_fused_config *cfg, dr_fused_state *st, const dr_fused_loop *lp) {
    float pm[5][5], pht[5][2], sv[3], h[2][3], qd, qb, det, ze, zn;
    if (!(cfg->rest_gate > 0.0f) || !(st->p[DR_FUSED_P22] > 0.0f) || !(cfg->kf_rest_r > 0.0f)) {
        return 1;
    }
    h[0][0] = lp->r00;
    h[0][1] = lp->r01;
    h[0][2] = lp->r02;
    h[1][0] = lp->r10;
    h[1][1] = lp->r11;
    h[1][2] = lp->r12;
    dr_fused_p_load(st, pm);
    dr_fused_kf_innovation((const float(*)[5])pm, (const float(*)[3])h, cfg->kf_rest_r, pht, sv);
    qd = cfg->kf_tilt_q * st->kf_t + cfg->kf_turn_q * st->turn * st->turn;
    qb = cfg->kf_bias_q * st->kf_t;
    sv[0] += qd + qb * (h[0][0] * h[0][0] + h[0][1] * h[0][1] + h[0][2] * h[0][2]);
    sv[1] += qb * (h[0][0] * h[1][0] + h[0][1] * h[1][1] + h[0][2] * h[1][2]);
    sv[2] += qd + qb * (h[1][0] * h[1][0] + h[1][1] * h[1][1] + h[1][2] * h[1][2]);
    det = sv[0] * sv[2] - sv[1] * sv[1];
    if (!(det > 0.0f)) {
        return 1; /* a broken covariance says nothing (its next step repairs it) */
    }
    ze = st->ah[DR_FUSED_AH_E];
    zn = st->ah[DR_FUSED_AH_N];
    return sv[2] * ze * ze - 2.0f * sv[1] * ze * zn + sv[0] * zn * zn < cfg->rest_gate * det;
}

/* Rest (codegen.fused's _rest): still (below rest_accel_g, or still_accel_g for a pedestrian's hand, idle_accel_g
 * for a vehicle's idling engine: broadband, slower than rest_speed_ms), the smoothed rate below rest_gyro_dps, the
 * horizontal force steady within the deadband and itself within it (a vehicle quiet after shaking, or below
 * rest_speed_ms: any the tilt/offset filter can take for its error), no fix saying it moves; for rest_time_s. */
static inline void dr_fused_rest(const dr_fused_config *cfg, dr_fused_state *st, dr_fused_loop *lp) {
    const float ae = lp->ae, an = lp->an;
    const float de = ae - st->ah[DR_FUSED_AH_E], dn = an - st->ah[DR_FUSED_AH_N];
    int still = st->var_f < cfg->rest_var;
    if (!still && lp->vehicle) {
        still = st->var_f < cfg->idle_var && lp->broadband && st->speed < cfg->rest_speed_ms;
    } else if (!still) {
        still = st->var_f < cfg->still_var;
    }
    if (still &&
        st->ws[DR_FUSED_WSX] * st->ws[DR_FUSED_WSX] + st->ws[DR_FUSED_WSY] * st->ws[DR_FUSED_WSY] +
                st->ws[DR_FUSED_WSZ] * st->ws[DR_FUSED_WSZ] <
            cfg->rest_w2 &&
        de * de + dn * dn < lp->db2 &&
        (ae * ae + an * an < lp->db2 ||
         (lp->vehicle && (lp->driven || st->speed < cfg->rest_speed_ms) && dr_fused_rest_explained(cfg, st, lp))) &&
        !(st->since_fix < cfg->gps_timeout_s && st->gps_ok > 0.0f)) {
        st->rest_s += lp->dt;
    } else {
        st->rest_s = 0.0f;
    }
    lp->rest = st->rest_s >= cfg->rest_time_s;
}

/* Steps or a vehicle (codegen.fused's _platform): walking when shaken, not at rest, in the gait band (auto) for
 * walk_time_s (vehicle_walk_time_s after a fast fix: a queue creeps in the gait band for seconds) and nothing says
 * a vehicle (a fast fix since the last rest, its own speed beyond a runner's); a
 * vehicle when shaken above it, a fast fix, or the platform. The steps stopped: so did the walker (speed 0). */
static inline void dr_fused_platform(const dr_fused_config *cfg, dr_fused_state *st, dr_fused_loop *lp) {
    const int platform = lp->platform, shaken = lp->shaken, broadband = lp->broadband, rest = lp->rest;
    int steps = platform != DR_FUSED_PLATFORM_VEHICLE && shaken && !rest &&
                (platform == DR_FUSED_PLATFORM_PEDESTRIAN ||
                 !(broadband || lp->fast || (lp->vehicle && st->speed > cfg->pedestrian_max_ms)));
    st->walk_s = steps ? st->walk_s + lp->dt : 0.0f;
    lp->walking = steps && ((lp->flags & DR_FUSED_WALKING) ||
                            st->walk_s >= (lp->drove ? cfg->vehicle_walk_time_s : cfg->walk_time_s));
    if (lp->walking) {
        lp->vehicle = 0;
        lp->drove = 0;
        lp->walked = DR_FUSED_WALKED;
    } else if (lp->fast || (shaken && broadband && platform != DR_FUSED_PLATFORM_PEDESTRIAN && !lp->walked)) {
        lp->vehicle = 1;
    }
    if (lp->vehicle) {
        lp->walked = 0;
    }
    if (rest) { /* a walker's stop keeps him a pedestrian (walked) */
        lp->driven = 0;
        lp->fast = 0;
    } else if (shaken && lp->vehicle) {
        lp->driven = DR_FUSED_SHAKEN;
    }
    if ((lp->flags & DR_FUSED_WALKING) && !lp->walking) {
        st->speed = 0.0f;
    }
}

/* The travel direction turned by the rate about Up, to second order; a walker's slow rotations (the hand) held
 * back, his turns taken at once (codegen.fused's _travel_direction). Then the sample's flags. */
static inline void dr_fused_travel_direction(const dr_fused_config *cfg, dr_fused_state *st, dr_fused_loop *lp) {
    const float dt = lp->dt;
    float r, da, ux, uy, inv;
    lp->turning = lp->flags & DR_FUSED_TURNING;
    r = lp->r20 * lp->wx + lp->r21 * lp->wy + lp->r22 * lp->wz;
    st->turn += dr_absf(r) * dt;
    st->rate_up += lp->alpha * (r - st->rate_up);
    da = r * dt;
    if (lp->walking && cfg->hold_rate > 0.0f) {
        float hold = dt * cfg->hold_rate;
        if (dr_absf(st->rate_up) > cfg->turn_start) {
            lp->turning = DR_FUSED_TURNING;
        } else if (dr_absf(st->rate_up) < cfg->turn_end) {
            lp->turning = 0;
        }
        st->held += da;
        da = lp->turning ? st->held : st->held * (hold < 1.0f ? hold : 1.0f);
        st->held -= da;
    } else {
        lp->turning = 0;
        da += st->held;
        st->held = 0.0f;
    }
    lp->flags = (lp->rest ? DR_FUSED_AT_REST : 0) | (lp->walking ? DR_FUSED_WALKING : 0) | lp->turning |
                (lp->vehicle ? DR_FUSED_VEHICLE : 0) | lp->driven | (lp->fast ? DR_FUSED_FAST : 0) | lp->walked |
                lp->drove;
    {
        float cd = 1.0f - 0.5f * da * da, sd = da * (1.0f - da * da * (1.0f / 6.0f));
        ux = cd * st->ux - sd * st->uy;
        uy = cd * st->uy + sd * st->ux;
    }
    inv = dr_inv_sqrt(ux * ux + uy * uy);
    st->ux = ux * inv;
    st->uy = uy * inv;
    lp->r = r;
}

/* A vehicle's speed (codegen.fused's _vehicle_speed): the along-track acceleration (the optional sliding median),
 * less its bias and the folded offsets' leak, through the deadband on its average over accel_tau_s, plus the
 * optional pull towards the GPS speed, integrated and floored at 0 (zr_v: without the floor). The deadband grows
 * from 0 at a fix to l over deadband_ramp_s (the tilt's gravity leak grows with the time since a fix). */
static inline void dr_fused_vehicle_speed(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st,
                                          const dr_fused_loop *lp) {
    const float dt = lp->dt;
    const float ramp = st->since_fix * cfg->inv_deadband_ramp;
    float deadband = kcfg->deadband_ms2;
    float a = lp->ae * st->ux + lp->an * st->uy;
    if (cfg->inv_deadband_ramp > 0.0f && ramp < 1.0f) {
        deadband *= ramp;
    }
    if (lp->median) { /* the seed's block median, sliding: the median of the last b along-track accelerations */
        float window[DR_FUSED_MEDIAN_MAX];
        int32_t slot = (int32_t)st->med_i, filled = (int32_t)st->med_n + 1, m;
        st->med[slot] = a;
        st->med_i = (float)(slot + 1 == lp->median ? 0 : slot + 1);
        if (filled > lp->median) {
            filled = lp->median;
        }
        st->med_n = (float)filled;
        for (m = 0; m < filled; m++) { /* after a restart the ring fills from slot 0 */
            window[m] = st->med[m];
        }
        a = dr_median(window, filled);
    }
    a -= st->bias + (st->nh_u0[DR_FUSED_NH_U0X] - st->ux) * st->nh_f[DR_FUSED_NH_FX] +
         (st->nh_u0[DR_FUSED_NH_U0Y] - st->uy) * st->nh_f[DR_FUSED_NH_FY];
    if (cfg->inv_accel_tau > 0.0f) { /* the deadband gates on the smoothed acceleration (not the road's) */
        float b = dt * cfg->inv_accel_tau;
        st->acc_lp += (b < 1.0f ? b : 1.0f) * (a - st->acc_lp);
        if (dr_absf(st->acc_lp) < deadband) {
            st->sb_lost += a * dt; /* what the deadband keeps out: the speed's noise at the next fix, no bias */
            a = 0.0f;
        }
    } else if (dr_absf(a) < deadband) { /* the board's deadband, on the along-track acceleration */
        st->sb_lost += a * dt;
        a = 0.0f;
    }
    a += (st->gps_speed - st->speed) * cfg->inv_speed_tau;
    st->speed += a * dt;
    st->zr_v += a * dt;
    if (st->speed < 0.0f) {
        st->speed = 0.0f;
    }
}

/* The along-track bias's random walk, (m/s^2)^2/s (codegen.fused's _bias_walk): the gravity leak's, or after a
 * calibration that moved, until a rest, speed_bias_noise^2. */
static inline float dr_fused_bias_walk(const dr_fused_config *cfg, const dr_fused_state *st) {
    return st->cal_moved > 0.0f ? cfg->speed_bias_q : cfg->kf_tilt_q;
}

/* A vehicle's speed for its position (codegen.fused's _kept_speed): the integrated speed (variance carried on from
 * the speed/bias filter) and the speed it keeps (the last fix's, variance kf_vel_sigma^2 + keep_q t) weighed by
 * their variances, bounded to [0, the speed last known + max_accel_ms2 t]. Returns m/s. */
static inline float dr_fused_kept_speed(const dr_fused_config *cfg, const dr_fused_state *st) {
    const float t = st->sk_t, known = st->keep_v;
    float s = st->speed, top;
    if (known >= 0.0f && cfg->keep_q > 0.0f) {
        const float v_s = st->sb_p[DR_FUSED_SB_PSS] - 2.0f * t * st->sb_p[DR_FUSED_SB_PSB] +
                          t * t * st->sb_p[DR_FUSED_SB_PBB] + cfg->speed_q * t +
                          dr_fused_bias_walk(cfg, st) * t * t * t * (1.0f / 3.0f);
        const float v_k = 0.5f * cfg->kf_vel_r + cfg->keep_q * t;
        s += v_s * dr_recip(v_s + v_k) * (known - s);
    }
    top = (known > 0.0f ? known : 0.0f) + cfg->max_accel_ms2 * t;
    return s > top ? top : s;
}

/* The speed along u (codegen.fused's _speed): at rest 0, after a vehicle's zero-velocity update of the position;
 * walking the learned walking speed; a pedestrian whose steps stopped without a rest: decaying to 0 over
 * stand_tau_s, never integrated; a vehicle's integrated (dr_fused_vehicle_speed). */
static inline void dr_fused_speed(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st,
                                  dr_fused_loop *lp) {
    const int rest = lp->rest, walking = lp->walking, walked = lp->walked;
    int i;
    if (rest || walking || walked) { /* the median ring restarts when the vehicle branch is entered again */
        st->med_i = 0.0f;
        st->med_n = 0.0f;
        st->acc_lp = 0.0f;
    }
    if (rest) {
        if (st->zr_t > 0.0f) {
            /* the speed it still had is the error gathered since its speed was last known; its integral along the
             * way, and what the floor at 0 kept out, taken back */
            float kz = st->zr_v * dr_recip(st->zr_t);
            st->pe += st->zr_c[DR_FUSED_ZR_CE] - kz * st->zr_p[DR_FUSED_ZR_PE];
            st->pn += st->zr_c[DR_FUSED_ZR_CN] - kz * st->zr_p[DR_FUSED_ZR_PN];
        }
        st->speed = 0.0f;
        st->zr_v = 0.0f;
        /* the speed known (0); a vehicle that stood starts from 0, not from the speed it kept; the gyro bias
         * re-learnt */
        st->sb_p[DR_FUSED_SB_PSS] = 0.0f;
        st->sb_p[DR_FUSED_SB_PSB] = 0.0f;
        st->sk_t = 0.0f;
        st->sb_lost = 0.0f;
        st->cal_moved = 0.0f;
        st->keep_v = -1.0f;
    } else if (walking || walked) {
        if (walking) {
            st->speed = st->walk_speed;
        } else {
            float decay = lp->dt * cfg->inv_stand_tau;
            st->speed -= st->speed * (decay < 1.0f ? decay : 1.0f);
        }
        st->zr_v = st->speed;
    } else {
        dr_fused_vehicle_speed(kcfg, cfg, st, lp);
    }
    lp->sp = rest || walking || walked ? st->speed : dr_fused_kept_speed(cfg, st);
    if (rest || walking || walked) {
        st->zr_t = 0.0f;
        st->zr_turn = 0.0f;
        for (i = 0; i < 2; i++) {
            st->zr_p[i] = 0.0f;
            st->zr_c[i] = 0.0f;
        }
    }
}

/* A vehicle's lateral update in an outage (codegen.fused's _lateral_update): no sideways sliding, so a_lat - s r =
 * leak - (s - s_true) r, gathered over nhc_period_s (dr_fused_nhc_update); restarted at a fix, a rest or a walk. */
static inline void dr_fused_lateral_update(const dr_fused_config *cfg, dr_fused_state *st, const dr_fused_loop *lp) {
    const float dt = lp->dt;
    if (!(cfg->nhc_var > 0.0f)) {
        return;
    }
    if (lp->rest || lp->walking || !lp->vehicle || st->since_fix < cfg->gps_timeout_s) {
        dr_fused_nhc_restart(st);
        return;
    }
    if (st->nh_u0[DR_FUSED_NH_U0X] == 0.0f && st->nh_u0[DR_FUSED_NH_U0Y] == 0.0f) {
        const float q_now[4] = {lp->q[0], lp->q[1], lp->q[2], lp->q[3]}; /* lp's address stays in the loop */
        dr_fused_nhc_start(cfg, st, q_now);
    }
    st->nh_t += dt;
    st->nh_z += (lp->an * st->ux - lp->ae * st->uy - st->speed * lp->r) * dt;
    st->nh_r += lp->r * dt;
    st->nh_i[DR_FUSED_NH_IX] += st->ux * dt;
    st->nh_i[DR_FUSED_NH_IY] += st->uy * dt;
    if (st->nh_t + 0.5f * dt >= cfg->nhc_period_s) { /* half a sample's margin: sums agree */
        dr_fused_nhc_update(cfg, st);
    }
}

/* What the next fix and rest update read (codegen.fused's _fix_integrals): the time towards the next rest update,
 * the kernel-frame velocity change and its integral, the integral of R(q)'s horizontal rows, the times since the
 * fix and since the tilt/offset filter's last prediction. */
static inline void dr_fused_fix_integrals(const dr_fused_config *cfg, dr_fused_state *st, const dr_fused_loop *lp) {
    const float dt = lp->dt, ae = lp->ae, an = lp->an;
    if (lp->rest && st->rest_s >= cfg->rest_time_s + cfg->rest_update_s) {
        st->zt += dt; /* a rest update every rest_update_s, after the rest's first (the end of the braking) */
    }
    st->dpx += (st->dvx + 0.5f * ae * dt) * dt;
    st->dpy += (st->dvy + 0.5f * an * dt) * dt;
    st->dvx += ae * dt;
    st->dvy += an * dt;
    st->m[DR_FUSED_M00] += lp->r00 * dt;
    st->m[DR_FUSED_M01] += lp->r01 * dt;
    st->m[DR_FUSED_M10] += lp->r10 * dt;
    st->m[DR_FUSED_M11] += lp->r11 * dt;
    st->m2[DR_FUSED_M02] += lp->r02 * dt;
    st->m2[DR_FUSED_M12] += lp->r12 * dt;
    st->since_fix += dt;
    st->sk_t += dt;
    st->kf_t += dt;
}

/* The position in true ENU and, for a vehicle, the integrals a zero-velocity update corrects it by
 * (codegen.fused's _advance_position). */
static inline void dr_fused_advance_position(const dr_fused_config *cfg, dr_fused_state *st,
                                             const dr_fused_loop *lp) {
    const float dt = lp->dt;
    const float ue = st->cos_t * st->ux - st->sin_t * st->uy;
    const float un = st->sin_t * st->ux + st->cos_t * st->uy;
    st->pe += lp->sp * ue * dt;
    st->pn += lp->sp * un * dt;
    if (!(lp->rest || lp->walking || lp->walked)) {
        float lag = (st->zr_v - lp->sp) * dt; /* what the floor and the kept speed moved it by, beyond zr_v */
        st->zr_turn += dr_absf(lp->r) * dt;
        st->zr_t += (1.0f + st->zr_turn * cfg->zupt_turn_weight) * dt;
        st->zr_p[DR_FUSED_ZR_PE] += st->zr_t * ue * dt;
        st->zr_p[DR_FUSED_ZR_PN] += st->zr_t * un * dt;
        st->zr_c[DR_FUSED_ZR_CE] += lag * ue;
        st->zr_c[DR_FUSED_ZR_CN] += lag * un;
    }
}

/* The tilt kept honest by gravity (minus the GPS motion acceleration while fixes arrive), then the attitude
 * integrated, q <- q (x) [1, omega dt / 2], renormalised (codegen.fused's _tilt_correction). */
static inline void dr_fused_tilt_correction(const dr_fused_config *cfg, const dr_fused_state *st, dr_fused_loop *lp) {
    const float dt = lp->dt;
    const float qw = lp->q[0], qx = lp->q[1], qy = lp->q[2], qz = lp->q[3];
    float gain, cx, cy, cz, nc2, inv, hx, hy, hz, nw, nx, ny, nz;
    float w0 = lp->wx, w1 = lp->wy, w2 = lp->wz;
    if (st->since_fix < cfg->gps_timeout_s) {
        gain = st->steady > 0.0f ? cfg->kp : 0.0f;
        cx = lp->fx - (lp->r00 * st->acc_e + lp->r10 * st->acc_n);
        cy = lp->fy - (lp->r01 * st->acc_e + lp->r11 * st->acc_n);
        cz = lp->fz - (lp->r02 * st->acc_e + lp->r12 * st->acc_n);
    } else {
        gain = cfg->kp_dark;
        cx = lp->fx;
        cy = lp->fy;
        cz = lp->fz;
    }
    nc2 = cx * cx + cy * cy + cz * cz;
    inv = dr_inv_sqrt(nc2);
    if (nc2 > 0.0f && dr_absf(nc2 * inv - DR_GRAVITY_MS2) < cfg->reject_ms2) {
        inv *= gain;
        w0 += (cy * lp->r22 - cz * lp->r21) * inv;
        w1 += (cz * lp->r20 - cx * lp->r22) * inv;
        w2 += (cx * lp->r21 - cy * lp->r20) * inv;
    }
    hx = 0.5f * w0 * dt;
    hy = 0.5f * w1 * dt;
    hz = 0.5f * w2 * dt;
    nw = qw - qx * hx - qy * hy - qz * hz;
    nx = qx + qw * hx + qy * hz - qz * hy;
    ny = qy + qw * hy - qx * hz + qz * hx;
    nz = qz + qw * hz + qx * hy - qy * hx;
    inv = dr_inv_sqrt(nw * nw + nx * nx + ny * ny + nz * nz);
    lp->q[0] = nw * inv;
    lp->q[1] = nx * inv;
    lp->q[2] = ny * inv;
    lp->q[3] = nz * inv;
}

/* At rest, every rest_update_s: the rest update (dr_fused_rest_update, on the state's attitude); out of rest its
 * clock restarts (codegen.fused's _rest_update_due). */
static inline void dr_fused_rest_update_due(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st,
                                            dr_fused_loop *lp) {
    if (!lp->rest) {
        st->zt = 0.0f;
    } else if (st->zt >= cfg->rest_update_s) {
        st->q[DR_FUSED_QW] = lp->q[0];
        st->q[DR_FUSED_QX] = lp->q[1];
        st->q[DR_FUSED_QY] = lp->q[2];
        st->q[DR_FUSED_QZ] = lp->q[3];
        dr_fused_rest_update(kcfg, cfg, st);
        lp->q[0] = st->q[DR_FUSED_QW];
        lp->q[1] = st->q[DR_FUSED_QX];
        lp->q[2] = st->q[DR_FUSED_QY];
        lp->q[3] = st->q[DR_FUSED_QZ];
    }
}

int dr_fused_process(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st, const int16_t *samples,
                     const int32_t *dt_us, int32_t count, float out[6]) {
    const float pe0 = st->pe, pn0 = st->pn;
    dr_fused_loop lp;
    int32_t k;
    int i;
    lp.platform = (int)cfg->platform;
    lp.flags = (int)st->flags;
    lp.vehicle = lp.platform == DR_FUSED_PLATFORM_VEHICLE || (lp.flags & DR_FUSED_VEHICLE);
    lp.driven = lp.flags & DR_FUSED_SHAKEN;
    lp.fast = (lp.flags & DR_FUSED_FAST) && lp.platform != DR_FUSED_PLATFORM_PEDESTRIAN;
    lp.walked = lp.flags & DR_FUSED_WALKED;
    lp.drove = lp.platform != DR_FUSED_PLATFORM_PEDESTRIAN ? lp.flags & DR_FUSED_DROVE : 0;
    lp.median = cfg->median > 0.0f && kcfg->block > 1 ? kcfg->block : 0;
    lp.db2 = kcfg->deadband_ms2 * kcfg->deadband_ms2;
    if (count < 1) {
        return DR_ERR_COUNT;
    }
    if (lp.median > DR_FUSED_MEDIAN_MAX) {
        return DR_ERR_BLOCK;
    }
    for (i = 0; i < 4; i++) {
        lp.q[i] = st->q[i];
    }
    lp.sp = st->speed;
    for (k = 0; k < count; k++) {
        dr_fused_sample_in(kcfg, st, &lp, samples + 6 * k, dt_us[k]);
        dr_fused_motion_statistics(cfg, st, &lp);
        dr_fused_horizontal_force(st, &lp);
        dr_fused_rest(cfg, st, &lp);
        dr_fused_platform(cfg, st, &lp);
        dr_fused_travel_direction(cfg, st, &lp);
        dr_fused_speed(kcfg, cfg, st, &lp);
        dr_fused_lateral_update(cfg, st, &lp);
        dr_fused_fix_integrals(cfg, st, &lp);
        dr_fused_advance_position(cfg, st, &lp);
        dr_fused_tilt_correction(cfg, st, &lp);
        dr_fused_rest_update_due(kcfg, cfg, st, &lp);
    }
    for (i = 0; i < 4; i++) {
        st->q[i] = lp.q[i];
    }
    st->flags = (float)lp.flags;
    out[0] = st->pe - pe0;
    out[1] = st->pn - pn0;
    out[2] = 0.0f;
    out[3] = lp.sp * (st->cos_t * st->ux - st->sin_t * st->uy);
    out[4] = lp.sp * (st->sin_t * st->ux + st->cos_t * st->uy);
    out[5] = 0.0f;
    return DR_OK;
}


/* The GPS-aided update of the tilt/offset filter at a fix (codegen.fused's tilt_and_offset_update): called with its
 * velocity, whether it has a course, and the seconds since the previous fix, before those are replaced. The
 * measurement noise counts the heading alignment's angle error: kf_vel_r / T^2 (1 + |dv_gps|^2 / |A|). */
static void dr_fused_filter(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, int moving, float t) {
    float h[2][3], x[5];
    float inv_t, gx, gy, z0, z1, norm2, norm;
    if (dr_fused_kf_start(cfg, st) || !dr_fused_kf_predict(cfg, st)) {
        return;
    }
    norm2 = st->align_c * st->align_c + st->align_s * st->align_s;
    if (!(st->gps_ok > 0.0f && moving && t > 0.0f && t < cfg->gps_timeout_s && norm2 > 0.0f &&
          norm2 >= cfg->kf_align_min * cfg->kf_align_min)) {
        return;
    }
    norm = dr_sqrt(norm2);
    inv_t = dr_recip(t);
    gx = ve - st->gps_ve;
    gy = vn - st->gps_vn;
    z0 = (st->dvx - (st->cos_t * gx + st->sin_t * gy)) * inv_t;
    z1 = (st->dvy - (-st->sin_t * gx + st->cos_t * gy)) * inv_t;
    h[0][0] = st->m[DR_FUSED_M00] * inv_t;
    h[0][1] = st->m[DR_FUSED_M01] * inv_t;
    h[0][2] = st->m2[DR_FUSED_M02] * inv_t;
    h[1][0] = st->m[DR_FUSED_M10] * inv_t;
    h[1][1] = st->m[DR_FUSED_M11] * inv_t;
    h[1][2] = st->m2[DR_FUSED_M12] * inv_t;
    dr_fused_kf_update(cfg, st, z0, z1, (const float(*)[3])h,
                       cfg->kf_vel_r * inv_t * inv_t * (1.0f + (gx * gx + gy * gy) * dr_recip(norm)), x);
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

/* The speed/bias filter's start and repair (codegen.fused's _speed_prior): the bias 0 +- nhc_leak_sigma (a
 * still calibration) or kf_bias_init_g (one that moved), uncorrelated with the speed, whose variance stays. */
static void dr_fused_speed_prior(const dr_fused_config *cfg, dr_fused_state *st) {
    const float pss = st->sb_p[DR_FUSED_SB_PSS];
    if (!(pss >= 0.0f && pss <= DR_FUSED_COV_MAX)) {
        st->sb_p[DR_FUSED_SB_PSS] = DR_FUSED_SPEED_UNKNOWN_VAR;
    }
    st->sb_p[DR_FUSED_SB_PSB] = 0.0f;
    st->sb_p[DR_FUSED_SB_PBB] = st->cal_moved > 0.0f ? cfg->kf_bias_var : cfg->nhc_leak_var;
}

/* The speed/bias filter's predict over t s, P <- F P F^T + Q, F = [[1, -t], [0, 1]], Q = diag(q_speed, q_bias)
 * (codegen.fused's _speed_predict). Returns 0 if the covariance went wrong (reset to the prior). */
int dr_fused_speed_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float q_speed, float q_bias) {
    const float pss = st->sb_p[DR_FUSED_SB_PSS], psb = st->sb_p[DR_FUSED_SB_PSB], pbb = st->sb_p[DR_FUSED_SB_PBB];
    st->sb_p[DR_FUSED_SB_PSS] = pss - 2.0f * t * psb + t * t * pbb + q_speed;
    st->sb_p[DR_FUSED_SB_PSB] = psb - t * pbb;
    st->sb_p[DR_FUSED_SB_PBB] = pbb + q_bias;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_SPEED, DR_FUSED_STEP_PREDICT, 1);
}

/* The speed/bias filter's update with the fix's speed, H = [1, 0], variance r (codegen.fused's _speed_correct):
 * P <- P - K S K^T as (I - K H) P, free of cancellation when the speed starts unknown. gain: K. Returns 0 if the
 * covariance went wrong (reset to the prior). */
int dr_fused_speed_correct(const dr_fused_config *cfg, dr_fused_state *st, float r, float gain[2]) {
    const float pss = st->sb_p[DR_FUSED_SB_PSS], psb = st->sb_p[DR_FUSED_SB_PSB], pbb = st->sb_p[DR_FUSED_SB_PBB];
    const float s = pss + r;
    float inv_s;
    if (!(s > 0.0f && s <= DR_FUSED_COV_MAX)) {
        return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_SPEED, DR_FUSED_STEP_UPDATE, 0);
    }
    inv_s = dr_recip(s);
    gain[0] = pss * inv_s;
    gain[1] = psb * inv_s;
    st->sb_p[DR_FUSED_SB_PSS] = gain[0] * r;
    st->sb_p[DR_FUSED_SB_PSB] = gain[1] * r;
    st->sb_p[DR_FUSED_SB_PBB] = pbb - gain[1] * psb;
    return dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_SPEED, DR_FUSED_STEP_UPDATE, 1);
}

/* A vehicle's speed/bias filter at a fix (codegen.fused's _speed_update): started on its first fix, predicted over
 * the sk_t s since the speed was known, updated with the fix's speed. gain: K. Returns 0 if nothing is to be fed
 * back (a covariance gone wrong). */
static int dr_fused_speed_update(const dr_fused_config *cfg, dr_fused_state *st, float gain[2]) {
    const float t = st->sk_t;
    float q_bias;
    if (!(st->sb_p[DR_FUSED_SB_PBB] > 0.0f)) {
        dr_fused_speed_prior(cfg, st);
        if (!dr_fused_covariance_checked(cfg, st, DR_FUSED_FILTER_SPEED, DR_FUSED_STEP_START, 1)) {
            return 0;
        }
    }
    q_bias = dr_fused_bias_walk(cfg, st) * t + cfg->kf_turn_q * st->turn * st->turn;
    /* the speed's noise: its random walk and what the deadband kept out of it (dr_fused_vehicle_speed) */
    if (!dr_fused_speed_predict(cfg, st, t, cfg->speed_q * t + st->sb_lost * st->sb_lost, q_bias)) {
        return 0;
    }
    return dr_fused_speed_correct(cfg, st, 0.5f * cfg->kf_vel_r, gain);
}

/* The heading alignment of the kernel frame to North from the velocity changes (codegen.fused's _fix_alignment), and
 * the motion acceleration over the interval into the kernel frame (a[0], a[1]). */
static inline void dr_fused_fix_alignment(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, float t,
                                          float a[2]) {
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
    inv_t = dr_recip(t);
    me = gx * inv_t;
    mn = gy * inv_t;
    a[0] = st->cos_t * me + st->sin_t * mn;
    a[1] = -st->sin_t * me + st->cos_t * mn;
}

/* A fix with a course (codegen.fused's _fix_course): the travel direction pulled towards it, and a walker's speed
 * towards the fix's, bounded by what people walk and run. */
static inline void dr_fused_fix_course(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn,
                                       float speed, float inv_speed) {
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
    if ((int)st->flags & DR_FUSED_WALKING) {
        float bounded = speed < cfg->pedestrian_max_ms ? speed : cfg->pedestrian_max_ms;
        st->walk_speed += cfg->walk_speed_gain * (bounded - st->walk_speed);
    }
}

/* The speed at a fix, t s after the previous one (codegen.fused's _fix_speed): a pedestrian's or a rest's pulled
 * (not integrated, so the interval says nothing of the bias), a vehicle's by the speed/bias filter, started from the
 * fix when the interval was not aimed (its travel direction not known at its start); then the speed kept is the
 * fix's. Before the tilt/offset filter's predict restarts st->turn, which the bias's noise reads. */
static inline void dr_fused_fix_speed(const dr_fused_config *cfg, dr_fused_state *st, float speed, float t,
                                      int aimed) {
    float e = speed - st->speed;
    if ((int)st->flags & (DR_FUSED_AT_REST | DR_FUSED_WALKING | DR_FUSED_WALKED)) {
        const float left = (1.0f - cfg->speed_gain) * e;
        st->speed += cfg->speed_gain * e;
        st->sb_p[DR_FUSED_SB_PSS] = left * left + 0.5f * cfg->kf_vel_r;
        st->sb_p[DR_FUSED_SB_PSB] = 0.0f;
    } else {
        float gain[2];
        if (!(aimed && t > 0.0f && t < cfg->gps_timeout_s)) { /* after an outage, before any fix, not aimed */
            st->sb_p[DR_FUSED_SB_PSS] = DR_FUSED_SPEED_UNKNOWN_VAR;
            st->sb_p[DR_FUSED_SB_PSB] = 0.0f;
        }
        if (dr_fused_speed_update(cfg, st, gain)) {
            st->speed += gain[0] * e;
            st->bias += gain[1] * e;
        }
    }
    st->keep_v = speed;
    st->sk_t = 0.0f;
    st->sb_lost = 0.0f;
}

/* What the next interval starts from (codegen.fused's _fix_restart): whether the motion acceleration (ae, an) is
 * steady, the fix's velocity and speed, the FAST flag, the integrals since the fix, the lateral filter restarted. */
static inline void dr_fused_fix_restart(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn,
                                        float speed, float ae, float an) {
    float de = ae - st->acc_e, dn = an - st->acc_n;
    int i;
    /* flags kept as margins (> 0 means yes): LLVM's Xtensa backend cannot select a constant pair (x ? 1.0f : 0.0f) */
    st->steady = cfg->steady_ms2 * cfg->steady_ms2 - (de * de + dn * dn);
    st->acc_e = ae;
    st->acc_n = an;
    st->gps_ve = ve;
    st->gps_vn = vn;
    st->gps_speed = speed;
    st->gps_ok = speed - cfg->min_speed_ms;
    /* faster than people run, or than people move without steps: a vehicle until it rests, one that drove until
     * it walks */
    if (speed > cfg->pedestrian_max_ms || (speed > cfg->carried_ms && !((int)st->flags & DR_FUSED_WALKING))) {
        st->flags = (float)((int)st->flags | DR_FUSED_FAST | DR_FUSED_DROVE);
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

/* One fix's Doppler velocity (codegen.fused's gps_update), in its steps. */
void dr_fused_gps(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn) {
    float s2 = ve * ve + vn * vn;
    float inv_speed = dr_inv_sqrt(s2);
    float speed = s2 * inv_speed;
    float t = st->since_fix;
    int moving = speed >= cfg->min_speed_ms;
    float a[2] = {0.0f, 0.0f};
    int aimed = st->gps_ok > 0.0f && (st->align_c != 0.0f || st->align_s != 0.0f); /* the direction was known */
    if (st->gps_ok > 0.0f && moving && t > 0.0f && t < cfg->gps_timeout_s) {
        dr_fused_fix_alignment(cfg, st, ve, vn, t, a);
    }
    if (moving) {
        dr_fused_fix_course(cfg, st, ve, vn, speed, inv_speed);
    }
    dr_fused_fix_speed(cfg, st, speed, t, aimed);
    if (cfg->kf_bias_var > 0.0f) {
        dr_fused_filter(cfg, st, ve, vn, moving, t);
    }
    dr_fused_fix_restart(cfg, st, ve, vn, speed, a[0], a[1]);
}
