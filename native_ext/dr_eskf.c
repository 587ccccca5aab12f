/*
 * dr_eskf.c: the error-state Kalman filter for a vehicle, float32 (dr_eskf.h; the specification is
 * codegen/kernel/eskf.py, whose function names the comments give). No float division and no libm: reciprocals,
 * square roots and the one exponential are written here (the ESP32's FPU has neither divide nor square root).
 */
#include "dr_eskf.h"

#include "dr_math.h"

#define N DR_ESKF_N
#define COV_MAX (1.0e30f)         /* an innovation variance beyond this (or not a number) is broken */
#define VAR_MAX (1.0e18f)         /* a variance beyond this is broken (the product of two stays a float32) */
#define CORR_SLACK (1.0e-3f)      /* |P_ij|^2 may exceed P_ii P_jj by this share (float32 rounding) */
#define POLAR_STEPS (4)           /* Newton steps onto the nearest rotation (0.5 rad off: 2e-10 left) */
#define SINCE_SLACK_S (1.0e-6f)   /* s: float32 rounding of the pseudo-measurement clock */
#define LN2 (0.693147180559945f)  /* ln 2 */
#define INV_LN2 (1.44269504088896f)
#define EXP_LIMIT (80.0f)         /* exp(-x) below this x; 0 beyond */
#define SATURATED_COUNTS (32767.0f) /* the int16 range's end: a clipped sample */
#define CAL_SUM_CHUNK (65536)     /* samples per exact int32 sum (|int16| * 65536 <= 2^31) */

/* The per-sample loop keeps its registers when the rare steps are calls, not inlined into it. */
#if defined(__GNUC__) || defined(__clang__)
#define DR_ESKF_NOINLINE __attribute__((noinline))
#else
#define DR_ESKF_NOINLINE
#endif

#ifdef DR_ESKF_OBSERVED
void dr_eskf_observed(const dr_eskf_state *st, int step);
#define DR_ESKF_OBSERVE(st, step) dr_eskf_observed((st), (step))
#else
#define DR_ESKF_OBSERVE(st, step) ((void)0)
#endif

void dr_eskf_config_init(dr_eskf_config *cfg) {
    cfg->cov_dt_s = 0.2f;
    cfg->nhc_dt_s = 0.4f;
    cfg->accel_noise = 0.05f;
    cfg->gyro_noise = 0.002f;
    cfg->accel_bias_walk = 2e-4f;
    cfg->gyro_bias_walk = 2e-5f;
    cfg->mount_walk = 2e-4f;
    cfg->turn_scale_walk = 1e-5f;
    cfg->gps_pos_sigma = 2.12f;
    cfg->gps_up_sigma = 3.2f;
    cfg->gps_tau_s = 60.0f;
    cfg->gps_white_sigma = 0.3f;
    cfg->gps_vel_sigma = 0.15f;
    cfg->gps_slow_sigma = 0.4f;
    cfg->nhc_sigma = 0.6f;
    cfg->saturation_excess_ms2 = 20.0f;
    cfg->nhc_lever_m = 1.0f;
    cfg->nhc_gate = 3.0f;
    cfg->nhc_min_speed = 1.0f;
    cfg->zupt_sigma = 0.02f;
    cfg->zupt_gate = 16.3f;
    cfg->zaru_sigma = 0.002f;
    cfg->rest_accel_g = 0.02f;
    cfg->rest_gyro_dps = 1.0f;
    cfg->rest_time_s = 0.5f;
    cfg->rest_speed_ms = 1.5f;
    cfg->rest_horizontal_ms2 = 0.3f;
    cfg->stat_tau_s = 0.5f;
    cfg->align_fixes = 5.0f;
    cfg->align_yaw_sigma_deg = 10.0f;
    cfg->align_scale = 1.25f;
    cfg->align_speed_ms = 2.0f;
    cfg->init_yaw_sigma_deg = 10.0f;
    cfg->init_tilt_sigma_deg = 0.3f;
    cfg->init_tilt_moving_deg = 2.0f;
    cfg->init_gyro_bias_dps = 0.1f;
    cfg->init_gyro_bias_moving_dps = 0.5f;
    cfg->init_accel_bias_ms2 = 0.3f;
    cfg->init_mount_sigma_deg = 5.0f;
    cfg->init_turn_scale = 0.03f;
}

static void zero3(float m[3][3]) {
    int i, j;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            m[i][j] = 0.0f;
        }
    }
}

static void eye3(float m[3][3]) {
    zero3(m);
    m[0][0] = m[1][1] = m[2][2] = 1.0f;
}

void dr_eskf_state_init(dr_eskf_state *st) {
    float *f = (float *)st;
    uint32_t i;
    for (i = 0; i < sizeof(dr_eskf_state) / sizeof(float); i++) {
        f[i] = 0.0f;
    }
    st->q[0] = 1.0f;
    st->al_u[0] = 1.0f;
    eye3(st->mount);
}

/* Returns exp(-x) for x >= 0 (a few ulp): 2^-k exp(-r) with x = k ln 2 + r, r in [0, ln 2). */
static float exp_neg(float x) {
    dr_bits scale;
    float r, term, sum;
    int32_t k, i;
    if (!(x < EXP_LIMIT)) {
        return 0.0f;
    }
    if (x <= 0.0f) {
        return 1.0f;
    }
    k = (int32_t)(x * INV_LN2);
    r = x - (float)k * LN2;
    term = 1.0f;
    sum = 1.0f;
    for (i = 1; i <= 9; i++) {
        term *= -r * dr_recip((float)i);
        sum += term;
    }
    scale.u = (uint32_t)(127 - k) << 23;
    return sum * scale.f;
}

/* ------------------------------------------------------------------------------------------------ start */

int dr_eskf_calibrate(const dr_config *kcfg, const dr_eskf_config *cfg, dr_eskf_state *st, const int16_t *samples,
                      int32_t count) {
    float total[6], mean[6], var[3], inv_n, norm, along;
    int32_t k, i;
    int moved = 0;
    (void)cfg;
    if (count < 1) {
        return DR_ESKF_ERR_COUNT;
    }
    for (i = 0; i < 6; i++) { /* explicit zeroing: an aggregate initialiser may become a memset call */
        total[i] = 0.0f;
    }
    dr_sum_counts(samples, count, 6, CAL_SUM_CHUNK, total);
    inv_n = dr_recip((float)count);
    for (i = 0; i < 3; i++) { /* the remap only permutes and negates: applied to the sums */
        mean[i] = kcfg->axis_sign[i] * total[kcfg->axis_source[i]] * inv_n;
        mean[3 + i] = kcfg->axis_sign[i] * total[3 + kcfg->axis_source[i]] * inv_n;
        var[i] = 0.0f;
    }
    for (k = 0; k < count; k++) {
        for (i = 0; i < 3; i++) {
            const float d = kcfg->axis_sign[i] * (float)samples[6 * k + kcfg->axis_source[i]] - mean[i];
            var[i] += d * d;
        }
    }
    for (i = 0; i < 3; i++) {
        if (var[i] * inv_n > kcfg->motion_limit_lsb2) {
            moved = 1;
        }
    }
    norm = dr_sqrt(mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2]);
    if (!(norm > 0.0f)) {
        return DR_ESKF_ERR_COUNT;
    }
    dr_quat_from_gravity(st->q, mean, norm);
    for (i = 0; i < 3; i++) {
        st->bg[i] = mean[3 + i] * kcfg->gyro_rads_per_lsb;
    }
    st->mean_f = norm * kcfg->accel_ms2_per_lsb;
    /* the accelerometer bias along the mean specific force: its length less g (an offset or scale error on the axis
     * that points Up, read as a vertical acceleration otherwise) */
    along = (st->mean_f - DR_GRAVITY_MS2) * dr_recip(norm);
    for (i = 0; i < 3; i++) {
        st->ba[i] = mean[i] * along;
    }
    st->gyro_moving = (float)moved; /* not moved ? 1.0f : 0.0f: LLVM's Xtensa backend cannot select that pair */
    return moved;
}

void dr_eskf_prior(const dr_eskf_config *cfg, dr_eskf_state *st) {
    float r[3][3], g[2][3], d[N], vb, tilt, bg, yaw, mount;
    int i, j;
    const int moving = st->gyro_moving != 0.0f;
    for (i = 0; i < N; i++) {
        for (j = 0; j < N; j++) {
            st->p[i][j] = 0.0f;
        }
    }
    tilt = (moving ? cfg->init_tilt_moving_deg : cfg->init_tilt_sigma_deg) * DR_RAD_PER_DEG;
    bg = cfg->init_gyro_bias_dps * DR_RAD_PER_DEG;
    yaw = cfg->init_yaw_sigma_deg * DR_RAD_PER_DEG;
    mount = cfg->init_mount_sigma_deg * DR_RAD_PER_DEG;
    vb = cfg->init_accel_bias_ms2 * cfg->init_accel_bias_ms2;
    for (i = 0; i < 3; i++) {
        d[DR_ESKF_ERR_P + i] = 4.0f * cfg->gps_pos_sigma * cfg->gps_pos_sigma;
        d[DR_ESKF_ERR_V + i] = 4.0f * cfg->gps_vel_sigma * cfg->gps_vel_sigma;
        d[DR_ESKF_ERR_TH + i] = tilt * tilt;
        d[DR_ESKF_ERR_BG + i] = bg * bg;
        d[DR_ESKF_ERR_BA + i] = vb;
        d[DR_ESKF_ERR_SG + i] = cfg->init_turn_scale * cfg->init_turn_scale;
        d[DR_ESKF_ERR_GE + i] = cfg->gps_pos_sigma * cfg->gps_pos_sigma;
    }
    d[DR_ESKF_ERR_P + 2] = cfg->gps_up_sigma * cfg->gps_up_sigma;
    d[DR_ESKF_ERR_TH + 2] = yaw * yaw;
    d[DR_ESKF_ERR_MU] = d[DR_ESKF_ERR_MU + 1] = mount * mount;
    d[DR_ESKF_ERR_GE + 2] = cfg->gps_up_sigma * cfg->gps_up_sigma;
    for (i = 0; i < N; i++) {
        st->p[i][i] = d[i];
    }
    dr_quat_to_matrix(st->q, r);
    if (moving) { /* a calibration in motion: the road's turn rate about Up went into the gyro bias */
        const float up = cfg->init_gyro_bias_moving_dps * DR_RAD_PER_DEG, extra = up * up - bg * bg;
        for (i = 0; i < 3; i++) {
            for (j = 0; j < 3; j++) {
                st->p[DR_ESKF_ERR_BG + i][DR_ESKF_ERR_BG + j] += extra * r[2][i] * r[2][j];
            }
        }
    }
    /* the tilt error tied to the accelerometer bias that calibration folded into it: G = [-R_N; R_E] / g */
    for (j = 0; j < 3; j++) {
        g[0][j] = -r[1][j] * DR_INV_GRAVITY;
        g[1][j] = r[0][j] * DR_INV_GRAVITY;
    }
    for (i = 0; i < 2; i++) {
        for (j = 0; j < 2; j++) {
            st->p[DR_ESKF_ERR_TH + i][DR_ESKF_ERR_TH + j] +=
                vb * (g[i][0] * g[j][0] + g[i][1] * g[j][1] + g[i][2] * g[j][2]);
        }
        for (j = 0; j < 3; j++) {
            st->p[DR_ESKF_ERR_TH + i][DR_ESKF_ERR_BA + j] = vb * g[i][j];
            st->p[DR_ESKF_ERR_BA + j][DR_ESKF_ERR_TH + i] = vb * g[i][j];
        }
    }
    DR_ESKF_OBSERVE(st, DR_ESKF_STEP_PRIOR);
}

/* The mounting from the body-frame velocity (x) and the body-frame Up made orthogonal to it (z); kept when still
 * (codegen.kernel.eskf._mounting_from_velocity). */
static void mounting_from_velocity(dr_eskf_state *st) {
    float r[3][3], x[3], z[3], k, dot;
    int i;
    dr_quat_to_matrix(st->q, r);
    for (i = 0; i < 3; i++) {
        x[i] = r[0][i] * st->vel[0] + r[1][i] * st->vel[1] + r[2][i] * st->vel[2];
    }
    dot = x[0] * x[0] + x[1] * x[1] + x[2] * x[2];
    if (dot < 1e-12f) {
        return;
    }
    k = dr_inv_sqrt(dot);
    for (i = 0; i < 3; i++) {
        x[i] *= k;
    }
    dot = r[2][0] * x[0] + r[2][1] * x[1] + r[2][2] * x[2];
    for (i = 0; i < 3; i++) {
        z[i] = r[2][i] - dot * x[i];
    }
    k = dr_inv_sqrt(z[0] * z[0] + z[1] * z[1] + z[2] * z[2]);
    for (i = 0; i < 3; i++) {
        z[i] *= k;
        st->mount[0][i] = x[i];
        st->mount[2][i] = z[i];
    }
    st->mount[1][0] = z[1] * x[2] - z[2] * x[1];
    st->mount[1][1] = z[2] * x[0] - z[0] * x[2];
    st->mount[1][2] = z[0] * x[1] - z[1] * x[0];
}

static void start(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                  float vn) {
    st->pos[0] = e;
    st->pos[1] = n;
    st->pos[2] = u;
    st->vel[0] = ve;
    st->vel[1] = vn;
    st->vel[2] = 0.0f;
    mounting_from_velocity(st);
    dr_eskf_prior(cfg, st);
    st->t_fix = t_s;
    st->acc_t = st->since_nhc = 0.0f;
    zero3(st->acc_a);
    zero3(st->acc_b);
    st->acc_dv[0] = st->acc_dv[1] = st->acc_dv[2] = 0.0f;
    st->aligned = 1.0f;
}

void dr_eskf_calibration_interval(dr_eskf_state *st, float ve, float vn, float seconds) {
    st->al_prev[0] = ve;
    st->al_prev[1] = vn;
    st->al_have_prev = 1.0f;
    st->al_s[0] = seconds;
    st->al_s[1] = 0.0f;
}

/* codegen.kernel.eskf._alignment_sums: the fix interval that ends now into the yaw fit's sums. */
static void alignment_sums(dr_eskf_state *st, float ve, float vn) {
    if (st->al_have_prev != 0.0f) {
        const float de = st->al_du[0], dn = st->al_du[1], se = st->al_s[0], sn = st->al_s[1];
        const float ve_ = ve - st->al_prev[0], vn_ = vn - st->al_prev[1];
        float *sum = st->al_sums;
        sum[DR_ESKF_AL_N] += 1.0f;
        sum[DR_ESKF_AL_DD] += de * de + dn * dn;
        sum[DR_ESKF_AL_SS] += se * se + sn * sn;
        sum[DR_ESKF_AL_DS] += de * se + dn * sn;
        sum[DR_ESKF_AL_DS + 1] += de * sn - dn * se;
        sum[DR_ESKF_AL_DV] += de * ve_ + dn * vn_;
        sum[DR_ESKF_AL_DV + 1] += de * vn_ - dn * ve_;
        sum[DR_ESKF_AL_SV] += se * ve_ + sn * vn_;
        sum[DR_ESKF_AL_SV + 1] += se * vn_ - sn * ve_;
        sum[DR_ESKF_AL_VV] += ve_ * ve_ + vn_ * vn_;
    }
    st->al_prev[0] = ve;
    st->al_prev[1] = vn;
    st->al_have_prev = 1.0f;
    st->al_du[0] = st->al_du[1] = 0.0f;
    st->al_s[0] = st->al_s[1] = 0.0f;
}

/* codegen.kernel.eskf.align: the least-squares fit dv = z du + c s over the fix intervals (alignment_fit); once it
 * has align_fixes intervals, its yaw's variance is within align_yaw_sigma_deg^2, |z| is plausible and the vehicle
 * moves, level the attitude by the offset b = -c / z (as it reads now: times al_u), turn it by z's angle and start.
 * Returns 1 if the filter started now. The half angle's cosine and sine come from z, no trigonometry. */
static int align(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                 float vn) {
    const float *sum = st->al_sums;
    float det, zr, zi, cr, ci, inv, rss, var, z2, lim, br, bi, oe, on, hx, hy, c, ch, sh, q[4], k;
    alignment_sums(st, ve, vn);
    {
        const float sdd = sum[DR_ESKF_AL_DD], sss = sum[DR_ESKF_AL_SS];
        const float dsr = sum[DR_ESKF_AL_DS], dsi = sum[DR_ESKF_AL_DS + 1];
        const float dvr = sum[DR_ESKF_AL_DV], dvi = sum[DR_ESKF_AL_DV + 1];
        const float svr = sum[DR_ESKF_AL_SV], svi = sum[DR_ESKF_AL_SV + 1];
        const float nfix = sum[DR_ESKF_AL_N];
        if (nfix < cfg->align_fixes || nfix < 3.0f || ve * ve + vn * vn < cfg->align_speed_ms * cfg->align_speed_ms) {
            return 0;
        }
        det = sdd * sss - (dsr * dsr + dsi * dsi);
        if (!(det > 1e-12f * sdd * sss) || !(det > 0.0f)) {
            return 0;
        }
        inv = dr_recip(det);
        zr = (sss * dvr - (dsr * svr - dsi * svi)) * inv; /* z = (Sss Sdv - Sds Ssv) / det */
        zi = (sss * dvi - (dsr * svi + dsi * svr)) * inv;
        cr = (sdd * svr - (dsr * dvr + dsi * dvi)) * inv; /* c = (Sdd Ssv - conj(Sds) Sdv) / det */
        ci = (sdd * svi - (dsr * dvi - dsi * dvr)) * inv;
        rss = sum[DR_ESKF_AL_VV] - (dvr * zr + dvi * zi + svr * cr + svi * ci);
        if (rss < 0.0f) {
            rss = 0.0f;
        }
        var = rss * dr_recip(2.0f * nfix - 4.0f) * sss * inv; /* the variance of z per real component */
        z2 = zr * zr + zi * zi;
        lim = cfg->align_yaw_sigma_deg * DR_RAD_PER_DEG;
        if (!(z2 > 0.0f) || var > lim * lim * z2 || z2 * cfg->align_scale * cfg->align_scale < 1.0f ||
            z2 > cfg->align_scale * cfg->align_scale) {
            return 0;
        }
    }
    /* the offset as it reads now: b = -c / z times al_u; the levelling (th_E, th_N) = (b_N, -b_E) / g */
    inv = dr_recip(z2);
    br = -(cr * zr + ci * zi) * inv;
    bi = -(ci * zr - cr * zi) * inv;
    oe = br * st->al_u[0] - bi * st->al_u[1];
    on = br * st->al_u[1] + bi * st->al_u[0];
    hx = 0.5f * on * DR_INV_GRAVITY;
    hy = -0.5f * oe * DR_INV_GRAVITY;
    q[0] = st->q[0] - hx * st->q[1] - hy * st->q[2]; /* q <- [1, hx, hy, 0] (x) q */
    q[1] = st->q[1] + hx * st->q[0] + hy * st->q[3];
    q[2] = st->q[2] + hy * st->q[0] - hx * st->q[3];
    q[3] = st->q[3] + hx * st->q[2] - hy * st->q[1];
    k = dr_inv_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    q[0] *= k;
    q[1] *= k;
    q[2] *= k;
    q[3] *= k;
    k = dr_inv_sqrt(z2);
    c = zr * k;
    ch = dr_sqrt(0.5f * (1.0f + c));
    sh = dr_sqrt(0.5f * (1.0f - c));
    if (zi < 0.0f) {
        sh = -sh;
    }
    st->q[0] = ch * q[0] - sh * q[3]; /* q <- [ch, 0, 0, sh] (x) q */
    st->q[1] = ch * q[1] - sh * q[2];
    st->q[2] = ch * q[2] + sh * q[1];
    st->q[3] = ch * q[3] + sh * q[0];
    start(cfg, st, t_s, e, n, u, ve, vn);
    return 1;
}

/* ------------------------------------------------------------------------------------------------ covariance */

int dr_eskf_covariance_usable(const float p[N][N]) {
    float limit[N];
    int i, j;
    /* variances in [0, VAR_MAX] (NaN fails); then |P_ij|^2 <= P_ii P_jj (1 + CORR_SLACK) for every pair, which also
     * bounds every entry and fails for NaN and infinity. The lower triangle is not read: every step writes it as
     * the upper's mirror (tests/test_eskf_c.py checks the whole matrix after every step). */
    for (i = 0; i < N; i++) {
        const float v = p[i][i];
        if (!(v >= 0.0f && v <= VAR_MAX)) {
            return 0;
        }
        limit[i] = v * (1.0f + CORR_SLACK);
    }
    for (i = 0; i < N; i++) {
        const float *row = p[i];
        const float li = limit[i];
        for (j = i + 1; j < N; j++) {
            const float v = row[j];
            if (!(v * v <= li * p[j][j])) {
                return 0;
            }
        }
    }
    return 1;
}

/* codegen.kernel.eskf._checked: 1 if the covariance is usable; else it returns to the prior, counted, and 0. */
static int checked(const dr_eskf_config *cfg, dr_eskf_state *st, int step) {
    DR_ESKF_OBSERVE(st, step);
    if (dr_eskf_covariance_usable((const float(*)[N])st->p)) {
        return 1;
    }
    st->cov_repairs += 1.0f;
    dr_eskf_prior(cfg, st);
    return 0;
}

/* Phi applied to one line x of P (a column: x = &p[0][j], stride N; a row: x = &p[i][0], stride 1), in place; only
 * the dp, dv and dtheta entries change (Phi = I + the blocks of codegen.kernel.eskf.transition):
 * x_p += T x_v - T/2 ([dV]x x_th + A x_ba),  x_v -= [dV]x x_th + A x_ba,  x_th -= A x_bg + B x_sg.
 * Two copies with the stride a constant (the ESP32 then addresses with immediate offsets). */
#define DR_ESKF_PHI_LINE(name, STRIDE)                                                                               \
    static void name(float *x, const float a[3][3], const float b[3][3], const float dv[3], float t) {              \
        const float th0 = x[(DR_ESKF_ERR_TH + 0) * (STRIDE)], th1 = x[(DR_ESKF_ERR_TH + 1) * (STRIDE)];            \
        const float th2 = x[(DR_ESKF_ERR_TH + 2) * (STRIDE)];                                                       \
        const float ba0 = x[(DR_ESKF_ERR_BA + 0) * (STRIDE)], ba1 = x[(DR_ESKF_ERR_BA + 1) * (STRIDE)];            \
        const float ba2 = x[(DR_ESKF_ERR_BA + 2) * (STRIDE)];                                                       \
        const float bg0 = x[(DR_ESKF_ERR_BG + 0) * (STRIDE)], bg1 = x[(DR_ESKF_ERR_BG + 1) * (STRIDE)];            \
        const float bg2 = x[(DR_ESKF_ERR_BG + 2) * (STRIDE)];                                                       \
        const float sg0 = x[(DR_ESKF_ERR_SG + 0) * (STRIDE)], sg1 = x[(DR_ESKF_ERR_SG + 1) * (STRIDE)];            \
        const float sg2 = x[(DR_ESKF_ERR_SG + 2) * (STRIDE)];                                                       \
        const float d0 = dv[1] * th2 - dv[2] * th1 + (a[0][0] * ba0 + a[0][1] * ba1 + a[0][2] * ba2);             \
        const float d1 = dv[2] * th0 - dv[0] * th2 + (a[1][0] * ba0 + a[1][1] * ba1 + a[1][2] * ba2);             \
        const float d2 = dv[0] * th1 - dv[1] * th0 + (a[2][0] * ba0 + a[2][1] * ba1 + a[2][2] * ba2);             \
        const float half_t = 0.5f * t;                                                                               \
        x[(DR_ESKF_ERR_P + 0) * (STRIDE)] += t * x[(DR_ESKF_ERR_V + 0) * (STRIDE)] - half_t * d0;                  \
        x[(DR_ESKF_ERR_P + 1) * (STRIDE)] += t * x[(DR_ESKF_ERR_V + 1) * (STRIDE)] - half_t * d1;                  \
        x[(DR_ESKF_ERR_P + 2) * (STRIDE)] += t * x[(DR_ESKF_ERR_V + 2) * (STRIDE)] - half_t * d2;                  \
        x[(DR_ESKF_ERR_V + 0) * (STRIDE)] -= d0;                                                                     \
        x[(DR_ESKF_ERR_V + 1) * (STRIDE)] -= d1;                                                                     \
        x[(DR_ESKF_ERR_V + 2) * (STRIDE)] -= d2;                                                                     \
        x[(DR_ESKF_ERR_TH + 0) * (STRIDE)] = th0 - (a[0][0] * bg0 + a[0][1] * bg1 + a[0][2] * bg2 +                 \
                                                    (b[0][0] * sg0 + b[0][1] * sg1 + b[0][2] * sg2));               \
        x[(DR_ESKF_ERR_TH + 1) * (STRIDE)] = th1 - (a[1][0] * bg0 + a[1][1] * bg1 + a[1][2] * bg2 +                 \
                                                    (b[1][0] * sg0 + b[1][1] * sg1 + b[1][2] * sg2));               \
        x[(DR_ESKF_ERR_TH + 2) * (STRIDE)] = th2 - (a[2][0] * bg0 + a[2][1] * bg1 + a[2][2] * bg2 +                 \
                                                    (b[2][0] * sg0 + b[2][1] * sg1 + b[2][2] * sg2));               \
    }
DR_ESKF_PHI_LINE(phi_column, N)
DR_ESKF_PHI_LINE(phi_row, 1)

/* The rows Phi changes: dp, dv, dtheta. */
#define CHANGED (DR_ESKF_ERR_TH + 3)

void dr_eskf_propagate_covariance(const dr_eskf_config *cfg, dr_eskf_state *st) {
    const float t = st->acc_t;
    const float qa = cfg->accel_noise * cfg->accel_noise;
    const float(*a)[3] = (const float(*)[3])st->acc_a;
    const float(*b)[3] = (const float(*)[3])st->acc_b;
    int i, j;
    /* M = Phi P: every column's first CHANGED rows. Then M Phi^T, which is symmetric: its rows from CHANGED on
     * are M's first CHANGED rows transposed (Phi^T leaves columns beyond CHANGED alone, so those entries of M are
     * final) and its bottom-right block is P's; only the first CHANGED rows need Phi^T, then the mirror. */
    for (j = 0; j < N; j++) {
        phi_column(&st->p[0][j], a, b, st->acc_dv, t);
    }
    for (i = 0; i < CHANGED; i++) {
        phi_row(&st->p[i][0], a, b, st->acc_dv, t);
    }
    for (i = 0; i < CHANGED; i++) {
        for (j = i + 1; j < CHANGED; j++) {
            const float v = 0.5f * (st->p[i][j] + st->p[j][i]);
            st->p[i][j] = st->p[j][i] = v;
        }
        for (j = CHANGED; j < N; j++) {
            st->p[j][i] = st->p[i][j];
        }
    }
    for (i = 0; i < 3; i++) {
        st->p[DR_ESKF_ERR_P + i][DR_ESKF_ERR_P + i] += qa * t * t * t * (1.0f / 3.0f);
        st->p[DR_ESKF_ERR_P + i][DR_ESKF_ERR_V + i] += qa * t * t * 0.5f;
        st->p[DR_ESKF_ERR_V + i][DR_ESKF_ERR_P + i] += qa * t * t * 0.5f;
        st->p[DR_ESKF_ERR_V + i][DR_ESKF_ERR_V + i] += qa * t + st->sat_dv * st->sat_dv;
        st->p[DR_ESKF_ERR_TH + i][DR_ESKF_ERR_TH + i] += cfg->gyro_noise * cfg->gyro_noise * t;
        st->p[DR_ESKF_ERR_BG + i][DR_ESKF_ERR_BG + i] += cfg->gyro_bias_walk * cfg->gyro_bias_walk * t;
        st->p[DR_ESKF_ERR_BA + i][DR_ESKF_ERR_BA + i] += cfg->accel_bias_walk * cfg->accel_bias_walk * t;
        st->p[DR_ESKF_ERR_SG + i][DR_ESKF_ERR_SG + i] += cfg->turn_scale_walk * cfg->turn_scale_walk * t;
    }
    for (i = 0; i < 2; i++) {
        st->p[DR_ESKF_ERR_MU + i][DR_ESKF_ERR_MU + i] += cfg->mount_walk * cfg->mount_walk * t;
    }
}

/* codegen.kernel.eskf.propagate: P over the interval since the last propagation; its sums restart. */
static void propagate(const dr_eskf_config *cfg, dr_eskf_state *st) {
    if (!(st->acc_t > 0.0f)) {
        return;
    }
    dr_eskf_propagate_covariance(cfg, st);
    st->acc_t = st->sat_dv = 0.0f;
    zero3(st->acc_a);
    zero3(st->acc_b);
    st->acc_dv[0] = st->acc_dv[1] = st->acc_dv[2] = 0.0f;
    checked(cfg, st, DR_ESKF_STEP_PREDICT);
}

/* ------------------------------------------------------------------------------------------------ measurements */

/* P's upper triangle onto its lower. */
static void mirror(float p[N][N]) {
    int i, j;
    for (i = 0; i < N; i++) {
        const float *row = p[i];
        float *column = &p[0][i];
        for (j = i + 1; (N - j) & 3; j++) {
            column[j * N] = row[j];
        }
        for (; j < N; j += 4) {
            column[j * N] = row[j];
            column[(j + 1) * N] = row[j + 1];
            column[(j + 2) * N] = row[j + 2];
            column[(j + 3) * N] = row[j + 3];
        }
    }
}

/* One scalar update on P's upper triangle only (the caller mirrors it after a measurement's rows):
 * u = P h^T, s = h u + r, P <- P - u u^T / s, dx <- dx + u (y - h dx) / s. Returns 0 (nothing changed) if s is not
 * a positive number within COV_MAX. */
static int scalar_update_upper(float p[N][N], float dx[N], const int32_t *h_index, const float *h_value, int32_t nnz,
                               float y, float r) {
    float u[N], s = r, hdx = 0.0f, inv_s, gain;
    int32_t i, j, k;
    for (i = 0; i < N; i++) {
        u[i] = 0.0f;
    }
    for (k = 0; k < nnz; k++) { /* column c of the symmetric P from the upper triangle: p[i][c] above, p[c][i] below */
        const int32_t c = h_index[k];
        const float h = h_value[k];
        for (i = 0; i <= c; i++) {
            u[i] += p[i][c] * h;
        }
        for (i = c + 1; i < N; i++) {
            u[i] += p[c][i] * h;
        }
    }
    for (k = 0; k < nnz; k++) {
        s += h_value[k] * u[h_index[k]];
        hdx += h_value[k] * dx[h_index[k]];
    }
    if (!(s > 0.0f && s <= COV_MAX)) {
        return 0;
    }
    inv_s = dr_recip(s);
    for (i = 0; i < N; i++) {
        const float ui = u[i] * inv_s;
        float *row = p[i];
        for (j = i; (N - j) & 3; j++) { /* then four at a time: the ESP32 code at -Os does not unroll */
            row[j] -= ui * u[j];
        }
        for (; j < N; j += 4) {
            row[j] -= ui * u[j];
            row[j + 1] -= ui * u[j + 1];
            row[j + 2] -= ui * u[j + 2];
            row[j + 3] -= ui * u[j + 3];
        }
    }
    gain = (y - hdx) * inv_s;
    for (i = 0; i < N; i++) {
        dx[i] += u[i] * gain;
    }
    return 1;
}

int dr_eskf_scalar_update(float p[N][N], float dx[N], const int32_t *h_index, const float *h_value, int32_t nnz,
                          float y, float r) {
    if (!scalar_update_upper(p, dx, h_index, h_value, nnz, y, r)) {
        return 0;
    }
    mirror(p);
    return 1;
}

/* codegen.kernel.eskf.inject: the error into the nominal state. */
static void inject(dr_eskf_state *st, const float dx[N]) {
    const float hx = 0.5f * dx[DR_ESKF_ERR_TH], hy = 0.5f * dx[DR_ESKF_ERR_TH + 1], hz = 0.5f * dx[DR_ESKF_ERR_TH + 2];
    const float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
    int i, j, k, step;
    for (i = 0; i < 3; i++) {
        st->pos[i] += dx[DR_ESKF_ERR_P + i];
        st->vel[i] += dx[DR_ESKF_ERR_V + i];
        st->bg[i] += dx[DR_ESKF_ERR_BG + i];
        st->ba[i] += dx[DR_ESKF_ERR_BA + i];
        st->sg[i] += dx[DR_ESKF_ERR_SG + i];
        st->ge[i] += dx[DR_ESKF_ERR_GE + i];
    }
    st->q[0] = qw - hx * qx - hy * qy - hz * qz;
    st->q[1] = qx + hx * qw + hy * qz - hz * qy;
    st->q[2] = qy + hy * qw + hz * qx - hx * qz;
    st->q[3] = qz + hz * qw + hx * qy - hy * qx;
    dr_quat_normalise(st->q);
    if (dx[DR_ESKF_ERR_MU] != 0.0f || dx[DR_ESKF_ERR_MU + 1] != 0.0f) {
        const float mp = dx[DR_ESKF_ERR_MU], my = dx[DR_ESKF_ERR_MU + 1];
        float c[3][3], cof[3][3], inv_det;
        /* C <- (I - [(0, mp, my)]x) C, then back onto the nearest rotation (the polar factor, which the reference
         * takes from the SVD) by Newton's iteration C <- (C + C^-T) / 2, C^-T = cofactor(C) / det C */
        for (j = 0; j < 3; j++) {
            c[0][j] = st->mount[0][j] + my * st->mount[1][j] - mp * st->mount[2][j];
            c[1][j] = st->mount[1][j] - my * st->mount[0][j];
            c[2][j] = st->mount[2][j] + mp * st->mount[0][j];
        }
        for (step = 0; step < POLAR_STEPS; step++) {
            for (i = 0; i < 3; i++) {
                const int i1 = i == 2 ? 0 : i + 1, i2 = i == 0 ? 2 : i - 1;
                for (j = 0; j < 3; j++) {
                    const int j1 = j == 2 ? 0 : j + 1, j2 = j == 0 ? 2 : j - 1;
                    cof[i][j] = c[i1][j1] * c[i2][j2] - c[i1][j2] * c[i2][j1];
                }
            }
            inv_det = dr_recip(c[0][0] * cof[0][0] + c[0][1] * cof[0][1] + c[0][2] * cof[0][2]);
            for (i = 0; i < 3; i++) {
                for (k = 0; k < 3; k++) {
                    c[i][k] = 0.5f * (c[i][k] + cof[i][k] * inv_det);
                }
            }
        }
        for (i = 0; i < 3; i++) {
            for (j = 0; j < 3; j++) {
                st->mount[i][j] = c[i][j];
            }
        }
    }
}

/* A sparse measurement row: up to two non-zeros (the GPS's, the rest's) or eight (the constraint's). */
typedef struct {
    int32_t index[8];
    float value[8];
    int32_t nnz;
} sparse_row;

/* codegen.kernel.eskf.update: scalar updates in sequence, then the error fed back. gate > 0: a row whose
 * innovation is beyond gate sigmas is left out. Returns 0 (nothing fed back) if the covariance went wrong. */
static int update(const dr_eskf_config *cfg, dr_eskf_state *st, const sparse_row *rows, const float *ys,
                  const float *rs, int count, float gate) {
    float dx[N];
    int i, k;
    for (i = 0; i < N; i++) {
        dx[i] = 0.0f;
    }
    for (k = 0; k < count; k++) {
        const sparse_row *h = rows + k;
        if (gate > 0.0f) {
            float innovation = ys[k], hph = rs[k];
            int a, b;
            for (a = 0; a < h->nnz; a++) {
                innovation -= h->value[a] * dx[h->index[a]];
                for (b = 0; b < h->nnz; b++) { /* the upper triangle: the lower is stale until the mirror */
                    const int32_t ia = h->index[a], ib = h->index[b];
                    hph += h->value[a] * (ia <= ib ? st->p[ia][ib] : st->p[ib][ia]) * h->value[b];
                }
            }
            if (innovation * innovation > gate * gate * hph) {
                continue;
            }
        }
        if (!scalar_update_upper(st->p, dx, h->index, h->value, h->nnz, ys[k], rs[k])) {
            st->cov_repairs += 1.0f;
            dr_eskf_prior(cfg, st);
            return 0;
        }
    }
    mirror(st->p);
    if (!checked(cfg, st, DR_ESKF_STEP_UPDATE)) {
        return 0;
    }
    inject(st, dx);
    return 1;
}

static void gps_update(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                       float vn) {
    sparse_row rows[5];
    float ys[5], rs[5], phi, speed, vs, rw;
    int i, j;
    propagate(cfg, st);
    /* the receiver's error over the time since the last fix (codegen.kernel.eskf.gps_error_step) */
    phi = exp_neg((t_s - st->t_fix) * dr_recip(cfg->gps_tau_s));
    for (i = DR_ESKF_ERR_GE; i < DR_ESKF_ERR_GE + 3; i++) {
        for (j = 0; j < N; j++) {
            st->p[i][j] *= phi;
            st->p[j][i] *= phi; /* the diagonal block twice: phi^2, as the reference's rows then columns */
        }
    }
    st->p[DR_ESKF_ERR_GE][DR_ESKF_ERR_GE] += cfg->gps_pos_sigma * cfg->gps_pos_sigma * (1.0f - phi * phi);
    st->p[DR_ESKF_ERR_GE + 1][DR_ESKF_ERR_GE + 1] += cfg->gps_pos_sigma * cfg->gps_pos_sigma * (1.0f - phi * phi);
    st->p[DR_ESKF_ERR_GE + 2][DR_ESKF_ERR_GE + 2] += cfg->gps_up_sigma * cfg->gps_up_sigma * (1.0f - phi * phi);
    for (i = 0; i < 3; i++) {
        st->ge[i] *= phi;
    }
    st->t_fix = t_s;
    checked(cfg, st, DR_ESKF_STEP_PREDICT);
    speed = dr_sqrt(ve * ve + vn * vn);
    st->gps_speed = speed;
    vs = speed > 0.0f ? cfg->gps_vel_sigma : cfg->gps_slow_sigma;
    rw = cfg->gps_white_sigma * cfg->gps_white_sigma;
    for (i = 0; i < 3; i++) {
        rows[i].nnz = 2;
        rows[i].index[0] = DR_ESKF_ERR_P + i;
        rows[i].index[1] = DR_ESKF_ERR_GE + i;
        rows[i].value[0] = rows[i].value[1] = 1.0f;
        rs[i] = rw;
    }
    for (i = 0; i < 2; i++) {
        rows[3 + i].nnz = 1;
        rows[3 + i].index[0] = DR_ESKF_ERR_V + i;
        rows[3 + i].value[0] = 1.0f;
        rs[3 + i] = vs * vs;
    }
    ys[0] = e - st->pos[0] - st->ge[0];
    ys[1] = n - st->pos[1] - st->ge[1];
    ys[2] = u - st->pos[2] - st->ge[2];
    ys[3] = ve - st->vel[0];
    ys[4] = vn - st->vel[1];
    update(cfg, st, rows, ys, rs, 5, 0.0f);
}

int dr_eskf_gps(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                float vn) {
    if (st->aligned != 0.0f) {
        gps_update(cfg, st, t_s, e, n, u, ve, vn);
        return 0;
    }
    return align(cfg, st, t_s, e, n, u, ve, vn);
}

/* C R^T and the vehicle-frame velocity C R^T v. */
static void vehicle_frame(const dr_eskf_state *st, float cr[3][3], float vv[3]) {
    float r[3][3];
    int i, j;
    dr_quat_to_matrix(st->q, r);
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            cr[i][j] = st->mount[i][0] * r[j][0] + st->mount[i][1] * r[j][1] + st->mount[i][2] * r[j][2];
        }
        vv[i] = cr[i][0] * st->vel[0] + cr[i][1] * st->vel[1] + cr[i][2] * st->vel[2];
    }
}

/* The constraint's rows, sparse: C R^T on dv, (C R^T)_i x v on dtheta, [v_veh]x's entries on dmu. */
static void nhc_sparse(const dr_eskf_state *st, sparse_row rows[2], float predicted[2]) {
    float cr[3][3], vv[3];
    const float *v = st->vel;
    int i, k;
    vehicle_frame(st, cr, vv);
    for (i = 0; i < 2; i++) {
        const float *c = cr[1 + i];
        sparse_row *h = rows + i;
        for (k = 0; k < 3; k++) {
            h->index[k] = DR_ESKF_ERR_V + k;
            h->value[k] = c[k];
            h->index[3 + k] = DR_ESKF_ERR_TH + k;
        }
        h->value[3] = c[1] * v[2] - c[2] * v[1];
        h->value[4] = c[2] * v[0] - c[0] * v[2];
        h->value[5] = c[0] * v[1] - c[1] * v[0];
        h->nnz = 7;
        predicted[i] = vv[1 + i];
    }
    /* [v_veh]x rows 1, 2 on (mu_p, mu_y): lateral (0, -vx), vertical (vx, 0) */
    rows[0].index[6] = DR_ESKF_ERR_MU + 1;
    rows[0].value[6] = -vv[0];
    rows[1].index[6] = DR_ESKF_ERR_MU;
    rows[1].value[6] = vv[0];
}

void dr_eskf_nhc_rows(const dr_eskf_state *st, float h[2][N], float predicted[2]) {
    sparse_row rows[2];
    int i, k;
    nhc_sparse(st, rows, predicted);
    for (i = 0; i < 2; i++) {
        for (k = 0; k < N; k++) {
            h[i][k] = 0.0f;
        }
        for (k = 0; k < rows[i].nnz; k++) {
            h[i][rows[i].index[k]] = rows[i].value[k];
        }
    }
}

static void nhc_update(const dr_eskf_config *cfg, dr_eskf_state *st) {
    sparse_row rows[2];
    float predicted[2], ys[2], rs[2], r;
    nhc_sparse(st, rows, predicted);
    r = cfg->nhc_sigma * cfg->nhc_sigma + cfg->nhc_lever_m * cfg->nhc_lever_m * st->rate2;
    ys[0] = -predicted[0];
    ys[1] = -predicted[1];
    rs[0] = rs[1] = r;
    update(cfg, st, rows, ys, rs, 2, cfg->nhc_gate);
}

/* codegen.kernel.eskf.zero_velocity_gate: v^T (P_vv + r I)^-1 v < zupt_gate, by a 3 x 3 Cholesky factor. */
static int zero_velocity_gate(const dr_eskf_config *cfg, const dr_eskf_state *st) {
    float s[3][3], l[3][3], z[3], inv_d[3], sum;
    const float r = cfg->zupt_sigma * cfg->zupt_sigma;
    int i, j, k;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) {
            s[i][j] = st->p[DR_ESKF_ERR_V + i][DR_ESKF_ERR_V + j];
        }
        s[i][i] += r;
    }
    for (i = 0; i < 3; i++) {
        for (j = 0; j <= i; j++) {
            sum = s[i][j];
            for (k = 0; k < j; k++) {
                sum -= l[i][k] * l[j][k];
            }
            if (i == j) {
                if (!(sum > 0.0f)) {
                    return 0;
                }
                inv_d[i] = dr_inv_sqrt(sum);
                l[i][i] = sum * inv_d[i];
            } else {
                l[i][j] = sum * inv_d[j];
            }
        }
    }
    sum = 0.0f; /* |L^-1 v|^2 */
    for (i = 0; i < 3; i++) {
        float zi = st->vel[i];
        for (k = 0; k < i; k++) {
            zi -= l[i][k] * z[k];
        }
        z[i] = zi * inv_d[i];
        sum += z[i] * z[i];
    }
    return sum < cfg->zupt_gate;
}

static void zero_velocity_update(const dr_eskf_config *cfg, dr_eskf_state *st) {
    sparse_row rows[6];
    float ys[6], rs[6];
    int i;
    for (i = 0; i < 3; i++) {
        rows[i].nnz = rows[3 + i].nnz = 1;
        rows[i].index[0] = DR_ESKF_ERR_V + i;
        rows[3 + i].index[0] = DR_ESKF_ERR_BG + i;
        rows[i].value[0] = rows[3 + i].value[0] = 1.0f;
        ys[i] = -st->vel[i];
        ys[3 + i] = st->ws[i];
        rs[i] = cfg->zupt_sigma * cfg->zupt_sigma;
        rs[3 + i] = cfg->zaru_sigma * cfg->zaru_sigma;
    }
    if (update(cfg, st, rows, ys, rs, 6, 0.0f)) {
        st->ws[0] = st->ws[1] = st->ws[2] = 0.0f; /* the bias correction leaves the samples from now on */
    }
}

/* codegen.kernel.eskf.covariance_step. */
static DR_ESKF_NOINLINE void covariance_step(const dr_eskf_config *cfg, dr_eskf_state *st) {
    float speed2;
    propagate(cfg, st);
    st->since_nhc += cfg->cov_dt_s;
    if (st->since_nhc + SINCE_SLACK_S < cfg->nhc_dt_s) {
        return;
    }
    st->since_nhc = 0.0f;
    speed2 = st->vel[0] * st->vel[0] + st->vel[1] * st->vel[1] + st->vel[2] * st->vel[2];
    if (st->rest_s >= cfg->rest_time_s && st->gps_speed < cfg->rest_speed_ms && zero_velocity_gate(cfg, st)) {
        zero_velocity_update(cfg, st);
    } else if (speed2 > cfg->nhc_min_speed * cfg->nhc_min_speed) {
        nhc_update(cfg, st);
    }
}

/* ------------------------------------------------------------------------------------------------ per sample */

/* The strapdown step per sample, written out by component (the ESP32 code at -Os does not unroll loops of three).
 * restrict: the state's fields may stay in registers across samples (nothing else reaches them meanwhile). */
int dr_eskf_process(const dr_config *restrict kcfg, const dr_eskf_config *restrict cfg, dr_eskf_state *restrict st,
                    const int16_t *restrict samples, const int32_t *restrict dt_us, int32_t count, float out[6]) {
    const float rest_var = (cfg->rest_accel_g * DR_GRAVITY_MS2) * (cfg->rest_accel_g * DR_GRAVITY_MS2);
    const float rest_w = cfg->rest_gyro_dps * DR_RAD_PER_DEG;
    const float horizontal2 = cfg->rest_horizontal_ms2 * cfg->rest_horizontal_ms2;
    const float inv_stat = dr_recip(cfg->stat_tau_s);
    const float saturated = SATURATED_COUNTS * kcfg->accel_ms2_per_lsb;
    const float ascale = kcfg->accel_ms2_per_lsb, gscale = kcfg->gyro_rads_per_lsb;
    const int32_t sx = kcfg->axis_source[0], sy = kcfg->axis_source[1], sz = kcfg->axis_source[2];
    const float gx_sign = kcfg->axis_sign[0], gy_sign = kcfg->axis_sign[1], gz_sign = kcfg->axis_sign[2];
    int32_t k;
    if (count < 0) {
        return DR_ESKF_ERR_COUNT;
    }
    for (k = 0; k < count; k++) {
        const int16_t *s = samples + 6 * k;
        const float dt = (float)dt_us[k] * DR_S_PER_US;
        const float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
        float fx, fy, fz, wx, wy, wz, r00, r01, r02, r10, r11, r12, r20, r21, r22, se, sn, su, turn, alpha, nf, d;
        float hx, hy, hz, nw, nx, ny, nz, inv, wsx, wsy, wsz;
        fx = gx_sign * (float)s[sx] * ascale;
        fy = gy_sign * (float)s[sy] * ascale;
        fz = gz_sign * (float)s[sz] * ascale;
        if (dr_absf(fx) >= saturated || dr_absf(fy) >= saturated || dr_absf(fz) >= saturated) {
            st->sat_dv += cfg->saturation_excess_ms2 * dt;
        }
        fx -= st->ba[0];
        fy -= st->ba[1];
        fz -= st->ba[2];
        wx = gx_sign * (float)s[3 + sx] * gscale - st->bg[0];
        wy = gy_sign * (float)s[3 + sy] * gscale - st->bg[1];
        wz = gz_sign * (float)s[3 + sz] * gscale - st->bg[2];
        r20 = 2.0f * (qx * qz - qw * qy);
        r21 = 2.0f * (qy * qz + qw * qx);
        r22 = 1.0f - 2.0f * (qx * qx + qy * qy);
        turn = r20 * wx + r21 * wy + r22 * wz;
        wx -= turn * st->sg[0];
        wy -= turn * st->sg[1];
        wz -= turn * st->sg[2];
        /* rest statistics over stat_tau_s */
        alpha = dt * inv_stat;
        if (alpha > 1.0f) {
            alpha = 1.0f;
        }
        nf = dr_sqrt(fx * fx + fy * fy + fz * fz);
        st->mean_f += alpha * (nf - st->mean_f);
        d = nf - st->mean_f;
        st->var_f += alpha * (d * d - st->var_f);
        wsx = st->ws[0] + alpha * (wx - st->ws[0]);
        wsy = st->ws[1] + alpha * (wy - st->ws[1]);
        wsz = st->ws[2] + alpha * (wz - st->ws[2]);
        st->ws[0] = wsx;
        st->ws[1] = wsy;
        st->ws[2] = wsz;
        r00 = 1.0f - 2.0f * (qy * qy + qz * qz);
        r01 = 2.0f * (qx * qy - qw * qz);
        r02 = 2.0f * (qx * qz + qw * qy);
        r10 = 2.0f * (qx * qy + qw * qz);
        r11 = 1.0f - 2.0f * (qx * qx + qz * qz);
        r12 = 2.0f * (qy * qz - qw * qx);
        se = r00 * fx + r01 * fy + r02 * fz;
        sn = r10 * fx + r11 * fy + r12 * fz;
        su = r20 * fx + r21 * fy + r22 * fz;
        st->ah[0] += alpha * (se - st->ah[0]);
        st->ah[1] += alpha * (sn - st->ah[1]);
        if (st->var_f < rest_var && wsx * wsx + wsy * wsy + wsz * wsz < rest_w * rest_w &&
            st->ah[0] * st->ah[0] + st->ah[1] * st->ah[1] < horizontal2) {
            st->rest_s += dt;
        } else {
            st->rest_s = 0.0f;
        }
        if (st->aligned != 0.0f) {
            const float ae = se, an = sn, au = su - DR_GRAVITY_MS2, td = turn * dt;
            st->pos[0] += (st->vel[0] + 0.5f * ae * dt) * dt;
            st->pos[1] += (st->vel[1] + 0.5f * an * dt) * dt;
            st->pos[2] += (st->vel[2] + 0.5f * au * dt) * dt;
            st->vel[0] += ae * dt;
            st->vel[1] += an * dt;
            st->vel[2] += au * dt;
            st->acc_a[0][0] += r00 * dt;
            st->acc_a[0][1] += r01 * dt;
            st->acc_a[0][2] += r02 * dt;
            st->acc_a[1][0] += r10 * dt;
            st->acc_a[1][1] += r11 * dt;
            st->acc_a[1][2] += r12 * dt;
            st->acc_a[2][0] += r20 * dt;
            st->acc_a[2][1] += r21 * dt;
            st->acc_a[2][2] += r22 * dt;
            st->acc_b[0][0] += r00 * td;
            st->acc_b[0][1] += r01 * td;
            st->acc_b[0][2] += r02 * td;
            st->acc_b[1][0] += r10 * td;
            st->acc_b[1][1] += r11 * td;
            st->acc_b[1][2] += r12 * td;
            st->acc_b[2][0] += r20 * td;
            st->acc_b[2][1] += r21 * td;
            st->acc_b[2][2] += r22 * td;
            st->acc_dv[0] += se * dt;
            st->acc_dv[1] += sn * dt;
            st->acc_dv[2] += su * dt;
            st->acc_t += dt;
        } else { /* the yaw fit's sums: the velocity change, and the heading turned by the rate about Up */
            const float td = turn * dt, ue = st->al_u[0] - st->al_u[1] * td, un = st->al_u[1] + st->al_u[0] * td;
            const float k = dr_inv_sqrt(ue * ue + un * un);
            st->al_du[0] += se * dt;
            st->al_du[1] += sn * dt;
            st->al_u[0] = ue * k;
            st->al_u[1] = un * k;
            st->al_s[0] += st->al_u[0] * dt;
            st->al_s[1] += st->al_u[1] * dt;
        }
        /* q <- q (x) [1, w dt / 2]; |q|^2 = 1 + e with e ~ |w dt|^2 / 4 (1e-4 at 5 rad/s): one Newton step of
         * 1/sqrt from 1 leaves 3e^2/8 (float32 rounding), and each step corrects what the last left */
        hx = 0.5f * wx * dt;
        hy = 0.5f * wy * dt;
        hz = 0.5f * wz * dt;
        nw = qw - hx * qx - hy * qy - hz * qz;
        nx = qx + hx * qw + hz * qy - hy * qz;
        ny = qy + hy * qw - hz * qx + hx * qz;
        nz = qz + hz * qw + hy * qx - hx * qy;
        inv = 1.5f - 0.5f * (nw * nw + nx * nx + ny * ny + nz * nz);
        st->q[0] = nw * inv;
        st->q[1] = nx * inv;
        st->q[2] = ny * inv;
        st->q[3] = nz * inv;
        st->rate2 = wx * wx + wy * wy + wz * wz;
        if (st->aligned != 0.0f && st->acc_t >= cfg->cov_dt_s) {
            covariance_step(cfg, st);
        }
    }
    out[0] = st->pos[0];
    out[1] = st->pos[1];
    out[2] = st->pos[2];
    out[3] = st->vel[0];
    out[4] = st->vel[1];
    out[5] = st->vel[2];
    return DR_ESKF_OK;
}
