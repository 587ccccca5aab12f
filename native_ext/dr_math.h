/*
 * dr_math.h: the small float32 math every kernel file shares (header only).
 *
 * The ESP32's FPU adds, multiplies and converts in hardware but has no divide and no square root: a `/` on floats
 * or sqrtf() becomes a call into libgcc/libm, which a MicroPython native module cannot link. So the kernel never
 * divides a float; it multiplies by a reciprocal from dr_recip() or dr_inv_sqrt(), Newton iterations from a
 * bit-level first guess, accurate to a few float32 ulp.
 */
#ifndef DR_MATH_H
#define DR_MATH_H

#include <stdint.h>

#define DR_GRAVITY_MS2 (9.80665f)            /* m/s^2, standard gravity */
#define DR_INV_GRAVITY (0.101971621f)        /* s^2/m, 1 / standard gravity */
#define DR_PI (3.14159265358979f)            /* rad */
#define DR_RAD_PER_DEG (0.0174532925199433f) /* rad per degree */
#define DR_RAD_PER_CYCLE (6.28318530717959f) /* rad per cycle (2 pi) */
#define DR_S_PER_US (1.0e-6f)                /* s per microsecond */
#define DR_TILT_DEGENERATE (1.0e-6f)         /* |f| + f_z below this share of |f|: the device is upside down */

/* The bits of a float and back, without breaking aliasing rules (C99 allows reading another union member). */
typedef union {
    float f;
    uint32_t u;
} dr_bits;

/* Returns |x|. */
static inline float dr_absf(float x) {
    return x < 0.0f ? -x : x;
}

/* Returns 1/sqrt(x) for x > 0 (a few ulp); 0 for x <= 0. */
static inline float dr_inv_sqrt(float x) {
    dr_bits b;
    float y;
    if (!(x > 0.0f)) {
        return 0.0f;
    }
    b.f = x;
    b.u = 0x5f375a86u - (b.u >> 1);
    y = b.f;
    y = y * (1.5f - 0.5f * x * y * y);
    y = y * (1.5f - 0.5f * x * y * y);
    y = y * (1.5f - 0.5f * x * y * y);
    return y;
}

/* Returns sqrt(x) for x >= 0 (a few ulp); 0 for x <= 0. */
static inline float dr_sqrt(float x) {
    return x * dr_inv_sqrt(x);
}

/* Returns 1/x for a normal x of either sign (a few ulp; exact for powers of two). x = m 2^e with m in [1, 2):
 * 1/m by Newton from the linear guess 24/17 - 8/17 m (relative error below 1/17, squared by each step), times 2^-e. */
static inline float dr_recip(float x) {
    dr_bits b, scale;
    float m, y;
    b.f = x;
    scale.u = (0x7f000000u - (b.u & 0x7f800000u)); /* 2^-e: biased exponent 254 - (127 + e) */
    b.u = (b.u & 0x007fffffu) | 0x3f800000u;       /* m in [1, 2) */
    m = b.f;
    y = 1.41176471f - 0.470588235f * m;
    y = y * (2.0f - m * y);
    y = y * (2.0f - m * y);
    y = y * (2.0f - m * y);
    y = y * (2.0f - m * y);
    y *= scale.f;
    return x < 0.0f ? -y : y;
}

/* Returns 1 if a is a positive multiple of b >= 1, else 0 (by subtraction: the Cortex-M0+ has no divide). */
static inline int dr_is_multiple(int32_t a, int32_t b) {
    if (a < 1 || b < 1) {
        return 0;
    }
    while (a >= b) {
        a -= b;
    }
    return a == 0;
}

/* Returns x rounded to the nearest integer, halves away from zero; |x| must fit an int32. */
static inline int32_t dr_round(float x) {
    return (int32_t)(x < 0.0f ? x - 0.5f : x + 0.5f);
}

/* Hamilton product r = p (x) q of quaternions [w, x, y, z]; r may not alias p or q. */
static inline void dr_quat_multiply(float r[4], const float p[4], const float q[4]) {
    r[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    r[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    r[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    r[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
}

/* Scales q to unit length (q = 0 becomes the identity). */
static inline void dr_quat_normalise(float q[4]) {
    float k = dr_inv_sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (k == 0.0f) {
        q[0] = 1.0f;
        q[1] = q[2] = q[3] = 0.0f;
        return;
    }
    q[0] *= k;
    q[1] *= k;
    q[2] *= k;
    q[3] *= k;
}

/* r = R(q) v: rotates the body vector v (any unit) into the earth frame by the unit quaternion q.
 * Uses t = 2 (q_v x v), r = v + w t + q_v x t (15 multiplies). r may alias v. */
static inline void dr_quat_rotate(float r[3], const float q[4], const float v[3]) {
    float tx = 2.0f * (q[2] * v[2] - q[3] * v[1]);
    float ty = 2.0f * (q[3] * v[0] - q[1] * v[2]);
    float tz = 2.0f * (q[1] * v[1] - q[2] * v[0]);
    float rx = v[0] + q[0] * tx + (q[2] * tz - q[3] * ty);
    float ry = v[1] + q[0] * ty + (q[3] * tx - q[1] * tz);
    float rz = v[2] + q[0] * tz + (q[1] * ty - q[2] * tx);
    r[0] = rx;
    r[1] = ry;
    r[2] = rz;
}

/* r = R(q), the rotation matrix of the unit quaternion q = [w, x, y, z] (body -> earth: r[i][j] is the earth axis
 * i's component of the body axis j). */
static inline void dr_quat_to_matrix(const float q[4], float r[3][3]) {
    const float qw = q[0], qx = q[1], qy = q[2], qz = q[3];
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

/* q = the shortest arc turning the mean specific force f (body, any unit) onto Up, yaw 0, with norm = |f| (the
 * caller has it): normalise([|f| + f_z, f_y, -f_x, 0]); upside down (f along -z, or f = 0) the half turn about x
 * (codegen.kernel.reference.tilt_from_gravity). */
static inline void dr_quat_from_gravity(float q[4], const float f[3], float norm) {
    const float w = norm + f[2];
    if (w <= DR_TILT_DEGENERATE * norm) {
        q[0] = 0.0f;
        q[1] = 1.0f;
        q[2] = 0.0f;
        q[3] = 0.0f;
        return;
    }
    q[0] = w;
    q[1] = f[1];
    q[2] = -f[0];
    q[3] = 0.0f;
    dr_quat_normalise(q);
}

/* Adds to total[0..axes-1] the sums of the first `axes` values of `count` rows of 6 int16 counts (a window's
 * ax ay az gx gy gz), summed exactly in int32 over `chunk` rows at a time (|int16| * chunk must fit an int32) and
 * moved to float per chunk: each kernel keeps the chunk its fallback mirrors, so their sums round alike. */
static inline void dr_sum_counts(const int16_t *samples, int32_t count, int32_t axes, int32_t chunk, float *total) {
    int32_t k, j, i, n;
    for (k = 0; k < count; k += n) {
        int32_t sum[6];
        for (i = 0; i < axes; i++) {
            sum[i] = 0;
        }
        n = count - k < chunk ? count - k : chunk;
        for (j = k; j < k + n; j++) {
            for (i = 0; i < axes; i++) {
                sum[i] += samples[6 * j + i];
            }
        }
        for (i = 0; i < axes; i++) {
            total[i] += (float)sum[i];
        }
    }
}

#endif /* DR_MATH_H */
