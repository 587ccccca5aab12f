/*
 * dr_fused.c: the fused real-time algorithm; see dr_fused.h and codegen/kernel/fused.py (the specification).
 */
#include "dr_fused.h"

#include "dr_board.h"
#include "dr_math.h"
#include "dr_median.h"

#define DR_FUSED_SUM_CHUNK (1024) /* samples summed in int32 before moving to float (1024 * 32768 < 2^31) */

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
    st->w2 = 0.0f;
    st->rest_s = 0.0f;
    st->speed = 0.0f;
    st->bax = 0.0f;
    st->bay = 0.0f;
    return code;
}

int dr_fused_process(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st, const int16_t *samples,
                     const int32_t *dt_us, int32_t count, float out[6]) {
    const float g = DR_GRAVITY_MS2;
    const float db2 = kcfg->deadband_ms2 * kcfg->deadband_ms2;
    float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
    float pe0 = st->pe, pn0 = st->pn;
    float ve, vn;
    int32_t k;
    int flags = (int)st->flags;
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
        float nf, alpha, d, r00, r01, r02, r10, r11, r12, r20, r21, r22, ae, an, r, da, ux, uy, inv, gain, cx, cy, cz,
            nc2;
        int i, rest, walking, turning = flags & DR_FUSED_TURNING;
        for (i = 0; i < 3; i++) {
            int32_t src = kcfg->axis_source[i];
            f[i] = kcfg->axis_sign[i] * (float)s[src] * kcfg->accel_ms2_per_lsb;
            c[i] = kcfg->axis_sign[i] * (float)s[3 + src];
            w[i] = (c[i] - st->gyro_bias_lsb[i]) * kcfg->gyro_rads_per_lsb;
        }
        f[0] -= st->bax;
        f[1] -= st->bay;
        /* motion statistics */
        nf = dr_sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        alpha = dt * cfg->inv_stat_tau;
        if (alpha > 1.0f) {
            alpha = 1.0f;
        }
        st->mean_f += alpha * (nf - st->mean_f);
        d = nf - st->mean_f;
        st->var_f += alpha * (d * d - st->var_f);
        st->w2 += alpha * (w[0] * w[0] + w[1] * w[1] + w[2] * w[2] - st->w2);
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
        /* rest: still, and no horizontal acceleration beyond the deadband (a smooth push is no rest) */
        if (st->var_f < cfg->rest_var && st->w2 < cfg->rest_w2 && ae * ae + an * an < db2) {
            st->rest_s += dt;
        } else {
            st->rest_s = 0.0f;
        }
        rest = st->rest_s >= cfg->rest_time_s;
        walking = st->var_f > cfg->walk_var;
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
        flags = (rest ? DR_FUSED_AT_REST : 0) | (walking ? DR_FUSED_WALKING : 0) | turning;
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
        if (rest || walking) { /* the median ring restarts when the vehicle branch is entered again */
            st->med_i = 0.0f;
            st->med_n = 0.0f;
        }
        if (rest) {
            st->speed = 0.0f;
            for (i = 0; i < 3; i++) {
                st->gyro_bias_lsb[i] += dt * cfg->inv_bias_tau * (c[i] - st->gyro_bias_lsb[i]);
            }
        } else if (walking) {
            st->speed = st->walk_speed;
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
            a -= st->bias;
            if (dr_absf(a) < kcfg->deadband_ms2) { /* the board's deadband, on the along-track acceleration */
                a = 0.0f;
            }
            st->speed += (a + (st->gps_speed - st->speed) * cfg->inv_speed_tau) * dt;
            if (st->speed < 0.0f) {
                st->speed = 0.0f;
            }
        }
        st->dpx += (st->dvx + 0.5f * ae * dt) * dt;
        st->dpy += (st->dvy + 0.5f * an * dt) * dt;
        st->dvx += ae * dt;
        st->dvy += an * dt;
        st->m[0] += r00 * dt;
        st->m[1] += r01 * dt;
        st->m[2] += r10 * dt;
        st->m[3] += r11 * dt;
        st->since_fix += dt;
        /* position, true ENU */
        ve = st->speed * (st->cos_t * st->ux - st->sin_t * st->uy);
        vn = st->speed * (st->sin_t * st->ux + st->cos_t * st->uy);
        st->pe += ve * dt;
        st->pn += vn * dt;
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

/* p[] index of the covariance entry (i, j), the upper triangle stored row by row (no table: no .rodata) */
static int dr_fused_pidx(int i, int j) {
    int lo = i < j ? i : j, hi = i < j ? j : i;
    return 4 * lo - ((lo * (lo - 1)) >> 1) + hi - lo;
}

/* The GPS-aided filter of the gravity leak and the horizontal accelerometer offsets (codegen.fused's
 * tilt_and_offset_update): called at each fix with its velocity, whether it has a course, and the seconds since
 * the previous fix, before those are replaced. */
static void dr_fused_filter(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, int moving, float t) {
    float h[2][2], pht[4][2], gain[4][2], x[4];
    float inv_t, gx, gy, z0, z1, s00, s01, s11, inv_det, i00, i01, i11, qd, qb, hx, hy, norm2;
    int i, j;
    if (!(cfg->kf_bias_var > 0.0f)) {
        return;
    }
    if (!(st->p[7] > 0.0f)) { /* the first fix after calibration: start with d = -R_h b */
        const float v = cfg->kf_bias_var;
        float qw = st->q[0], qx = st->q[1], qy = st->q[2], qz = st->q[3];
        float r00 = 1.0f - 2.0f * (qy * qy + qz * qz), r01 = 2.0f * (qx * qy - qw * qz);
        float r10 = 2.0f * (qx * qy + qw * qz), r11 = 1.0f - 2.0f * (qx * qx + qz * qz);
        st->p[0] = v * (r00 * r00 + r01 * r01);
        st->p[1] = v * (r00 * r10 + r01 * r11);
        st->p[2] = -v * r00;
        st->p[3] = -v * r01;
        st->p[4] = v * (r10 * r10 + r11 * r11);
        st->p[5] = -v * r10;
        st->p[6] = -v * r11;
        st->p[7] = v;
        st->p[8] = 0.0f;
        st->p[9] = v;
        return;
    }
    if (!(t > 0.0f)) {
        return;
    }
    qd = cfg->kf_tilt_q * t + cfg->kf_turn_q * st->turn * st->turn;
    qb = cfg->kf_bias_q * t;
    st->p[0] += qd;
    st->p[4] += qd;
    st->p[7] += qb;
    st->p[9] += qb;
    norm2 = st->align_c * st->align_c + st->align_s * st->align_s;
    if (!(st->gps_ok > 0.0f && moving && t < cfg->gps_timeout_s && norm2 >= cfg->kf_align_min * cfg->kf_align_min)) {
        return;
    }
    inv_t = dr_recip(t);
    gx = ve - st->gps_ve;
    gy = vn - st->gps_vn;
    z0 = (st->dvx - (st->cos_t * gx + st->sin_t * gy)) * inv_t;
    z1 = (st->dvy - (-st->sin_t * gx + st->cos_t * gy)) * inv_t;
    h[0][0] = st->m[0] * inv_t;
    h[0][1] = st->m[1] * inv_t;
    h[1][0] = st->m[2] * inv_t;
    h[1][1] = st->m[3] * inv_t;
    for (i = 0; i < 4; i++) { /* P H^T, H = [I2 | h] */
        float pi2 = st->p[dr_fused_pidx(i, 2)], pi3 = st->p[dr_fused_pidx(i, 3)];
        for (j = 0; j < 2; j++) {
            pht[i][j] = st->p[dr_fused_pidx(i, j)] + pi2 * h[j][0] + pi3 * h[j][1];
        }
    }
    s00 = pht[0][0] + h[0][0] * pht[2][0] + h[0][1] * pht[3][0] + cfg->kf_vel_r * inv_t * inv_t;
    s01 = pht[0][1] + h[0][0] * pht[2][1] + h[0][1] * pht[3][1];
    s11 = pht[1][1] + h[1][0] * pht[2][1] + h[1][1] * pht[3][1] + cfg->kf_vel_r * inv_t * inv_t;
    inv_det = dr_recip(s00 * s11 - s01 * s01);
    i00 = s11 * inv_det;
    i01 = -s01 * inv_det;
    i11 = s00 * inv_det;
    for (i = 0; i < 4; i++) { /* K = P H^T S^-1, x = K z */
        gain[i][0] = pht[i][0] * i00 + pht[i][1] * i01;
        gain[i][1] = pht[i][0] * i01 + pht[i][1] * i11;
        x[i] = gain[i][0] * z0 + gain[i][1] * z1;
    }
    for (i = 0; i < 4; i++) {
        for (j = i; j < 4; j++) {
            st->p[dr_fused_pidx(i, j)] -= gain[i][0] * pht[j][0] + gain[i][1] * pht[j][1];
        }
    }
    st->bax += x[2];
    st->bay += x[3];
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
}

void dr_fused_position(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, float de, float dn) {
    const float t = st->since_fix;
    float x, phi, pxx, pxe, pee, cx, cy, ae, an, ee, en, s, inv_s, kx, ke;
    if (!(cfg->pos_var > 0.0f)) {
        return;
    }
    if (!(st->fix_pxx > 0.0f && t > 0.0f && t < cfg->gps_timeout_s)) { /* (re)start at the fix itself */
        st->fix_ae = 0.0f;
        st->fix_an = 0.0f;
        st->fix_ee = 0.0f;
        st->fix_en = 0.0f;
        st->fix_pxx = cfg->pos_var;
        st->fix_pee = cfg->pos_var;
        st->fix_pxe = -cfg->pos_var;
        return;
    }
    x = t * cfg->inv_pos_tau;
    phi = 1.0f - x * (1.0f - x * (0.5f - x * (1.0f / 6.0f))); /* exp(-x), cubic Taylor (x <= gps_timeout / tau) */
    pxx = st->fix_pxx + cfg->pos_step_q * t * t;
    pxe = phi * st->fix_pxe;
    pee = phi * phi * st->fix_pee + cfg->pos_var * (1.0f - phi * phi);
    /* the IMU's correction to the trapezoid T (v0 + v1) / 2, rotated into true ENU below */
    cx = st->dpx - 0.5f * t * st->dvx;
    cy = st->dpy - 0.5f * t * st->dvy;
    ae = st->fix_ae + 0.5f * t * (st->gps_ve + ve) + (st->cos_t * cx - st->sin_t * cy) - de;
    an = st->fix_an + 0.5f * t * (st->gps_vn + vn) + (st->sin_t * cx + st->cos_t * cy) - dn;
    ee = phi * st->fix_ee;
    en = phi * st->fix_en;
    s = pxx + 2.0f * pxe + pee;
    inv_s = dr_recip(s);
    kx = (pxx + pxe) * inv_s;
    ke = (pxe + pee) * inv_s;
    st->fix_ae = ae - kx * (ae + ee);
    st->fix_an = an - kx * (an + en);
    st->fix_ee = ee - ke * (ae + ee);
    st->fix_en = en - ke * (an + en);
    st->fix_pxx = pxx - kx * kx * s;
    st->fix_pxe = pxe - kx * ke * s;
    st->fix_pee = pee - ke * ke * s;
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
        if (norm > 0.0f) {
            st->cos_t = st->align_c * norm;
            st->sin_t = st->align_s * norm;
        }
        /* the motion acceleration over the interval, into the kernel frame */
        inv_t = dr_recip(t);
        me = gx * inv_t;
        mn = gy * inv_t;
        ae = st->cos_t * me + st->sin_t * mn;
        an = -st->sin_t * me + st->cos_t * mn;
    }
    dr_fused_filter(cfg, st, ve, vn, moving, t);
    de = ae - st->acc_e;
    dn = an - st->acc_n;
    /* flags kept as margins (> 0 means yes): LLVM's Xtensa backend cannot select a constant pair (x ? 1.0f : 0.0f) */
    st->steady = cfg->steady_ms2 * cfg->steady_ms2 - (de * de + dn * dn);
    st->acc_e = ae;
    st->acc_n = an;
    if (moving) {
        float gx = (st->cos_t * ve + st->sin_t * vn) * inv_speed;
        float gy = (-st->sin_t * ve + st->cos_t * vn) * inv_speed;
        float ux = st->ux + cfg->heading_gain * (gx - st->ux);
        float uy = st->uy + cfg->heading_gain * (gy - st->uy);
        float norm = dr_inv_sqrt(ux * ux + uy * uy);
        if (norm > 0.0f) {
            st->ux = ux * norm;
            st->uy = uy * norm;
        }
        if (flags & DR_FUSED_WALKING) {
            st->walk_speed += cfg->walk_speed_gain * (speed - st->walk_speed);
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
    st->dvx = 0.0f;
    st->dvy = 0.0f;
    st->dpx = 0.0f;
    st->dpy = 0.0f;
    for (i = 0; i < 4; i++) {
        st->m[i] = 0.0f;
    }
    st->turn = 0.0f;
    st->since_fix = 0.0f;
}
