/*
 * test_kernel.c: the kernel's C unit tests, built with -fsanitize=address,undefined by tests/test_kernel_c.py
 * (and runnable by hand: cc -std=c99 -I.. -I<dir with dr_board.h> test_kernel.c ../dr_*.c). Exit status 0 = pass.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dr_board.h"
#include "dr_geo.h"
#include "dr_kernel.h"
#include "dr_math.h"
#include "dr_median.h"

#define MAX_SAMPLES (4096)

static int failures = 0;

#define CHECK(cond)                                                              \
    do {                                                                         \
        if (!(cond)) {                                                           \
            fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond); \
            failures++;                                                          \
        }                                                                        \
    } while (0)

static int16_t samples[6 * MAX_SAMPLES];
static int32_t dt_us[MAX_SAMPLES];
static float scratch[3 * MAX_SAMPLES];
static float medians[3 * MAX_SAMPLES];

static uint32_t rng_state = 12345u;
static uint32_t rng_next(void) {
    rng_state = rng_state * 1664525u + 1013904223u;
    return rng_state >> 8;
}

static int cmp_float(const void *a, const void *b) {
    float x = *(const float *)a, y = *(const float *)b;
    return (x > y) - (x < y);
}

static void test_math(void) {
    float x;
    for (x = 1e-6f; x < 1e6f; x *= 1.37f) {
        CHECK(fabsf(dr_recip(x) * x - 1.0f) < 4e-7f);
        CHECK(fabsf(dr_inv_sqrt(x) * dr_inv_sqrt(x) * x - 1.0f) < 6e-7f);
        CHECK(dr_recip(-x) == -dr_recip(x));
    }
    CHECK(dr_inv_sqrt(0.0f) == 0.0f && dr_inv_sqrt(-1.0f) == 0.0f);
    for (x = -1.5707963f; x <= 1.5707963f; x += 0.01f) {
        CHECK(fabsf(dr_sin_half_pi(x) - (float)sin((double)x)) < 3e-7f);
    }
    CHECK(dr_round(2.5f) == 3 && dr_round(-2.5f) == -3 && dr_round(0.49f) == 0);
}

static void test_median(void) {
    static const int32_t blocks[] = {1, 2, 3, 16, 512};
    float x[512], sorted[512], out[512];
    int32_t bi, i;
    for (bi = 0; bi < 5; bi++) {
        int32_t b = blocks[bi], count = (512 / b) * b, j;
        for (i = 0; i < count; i++) {
            x[i] = (float)((int32_t)(rng_next() % 2001u) - 1000) * 0.125f;
        }
        memcpy(sorted, x, sizeof(x));
        CHECK(dr_block_median(x, count, b, out) == count / b);
        for (j = 0; j < count / b; j++) {
            float m;
            qsort(sorted + j * b, (size_t)b, sizeof(float), cmp_float);
            m = (b & 1) ? sorted[j * b + b / 2] : (sorted[j * b + b / 2 - 1] + sorted[j * b + b / 2]) * 0.5f;
            CHECK(out[j] == m);
        }
    }
    CHECK(dr_block_median(x, 17, 16, out) == -1);
    CHECK(dr_block_median(x, 16, 0, out) == -1);
}

static void test_config(void) {
    dr_config cfg;
    dr_config_init(&cfg);
    CHECK(cfg.block == DR_BLOCK_SAMPLES && cfg.window == DR_WINDOW_SAMPLES);
    CHECK(dr_config_set(&cfg, 0, 16, 16384.0f, 131.0f, 0.03f, 0.02f) == DR_ERR_BLOCK);
    CHECK(dr_config_set(&cfg, 16, 500, 16384.0f, 131.0f, 0.03f, 0.02f) == DR_ERR_WINDOW);
    CHECK(dr_config_set(&cfg, 16, 512, -1.0f, 131.0f, 0.03f, 0.02f) == DR_ERR_RANGE);
    CHECK(dr_config_set(&cfg, 16, 512, 16384.0f, 131.0f, 0.03f, 0.02f) == DR_OK);
    CHECK(cfg.accel_ms2_per_lsb * 16384.0f == DR_GRAVITY_MS2);
    {
        dr_state st;
        float out[6];
        dr_config bad = cfg;
        bad.axis_source[1] = 7; /* a config read from a corrupted buffer must not index outside a sample */
        CHECK(dr_process(&bad, &st, scratch, samples, dt_us, 16, out, 0) == DR_ERR_RANGE);
        CHECK(dr_calibrate(&bad, &st, samples, 16) == DR_ERR_RANGE);
        bad = cfg;
        bad.block = 0;
        CHECK(dr_process(&bad, &st, scratch, samples, dt_us, 16, out, 0) == DR_ERR_RANGE);
    }
}

static void test_constant_acceleration(void) {
    dr_config cfg;
    dr_state st;
    float out[6];
    double a = 4096.0 * 9.80665 / 16384.0, t = 512 * 0.005;
    int32_t k;
    dr_config_init(&cfg);
    CHECK(dr_config_set(&cfg, 16, 512, 16384.0f, 131.0f, 0.03125f, 0.02f) == DR_OK);
    dr_state_init(&st);
    for (k = 0; k < 512; k++) {
        memset(samples + 6 * k, 0, 6 * sizeof(int16_t));
        samples[6 * k] = 4096;
        samples[6 * k + 2] = 16384;
        dt_us[k] = 5000;
    }
    CHECK(dr_process(&cfg, &st, scratch, samples, dt_us, 512, out, medians) == DR_OK);
    CHECK(fabs(out[0] - 0.5 * a * t * t) < 64 * 6e-8 * 0.5 * a * t * t);
    CHECK(fabs(out[3] - a * t) < 64 * 6e-8 * a * t);
    CHECK(out[1] == 0.0f && out[2] == 0.0f && out[4] == 0.0f && out[5] == 0.0f);
    CHECK(dr_process(&cfg, &st, scratch, samples, dt_us, 500, out, 0) == DR_ERR_COUNT);
    CHECK(dr_process(&cfg, &st, scratch, samples, dt_us, 0, out, 0) == DR_ERR_COUNT);
}

static void test_rotation(void) {
    dr_config cfg;
    dr_state st;
    float out[6], yaw;
    int32_t k;
    dr_config_init(&cfg);
    CHECK(dr_config_set(&cfg, 16, 512, 16384.0f, 131.0f, 0.03125f, 0.02f) == DR_OK);
    dr_state_init(&st);
    for (k = 0; k < 208; k++) {
        memset(samples + 6 * k, 0, 6 * sizeof(int16_t));
        samples[6 * k + 2] = 16384;
        samples[6 * k + 5] = 90 * 131;
        dt_us[k] = 5000;
    }
    CHECK(dr_process(&cfg, &st, scratch, samples, dt_us, 208, out, 0) == DR_OK);
    yaw = 2.0f * atan2f(st.q[3], st.q[0]);
    CHECK(fabsf(yaw - 1.5707963f * 1.04f) < 1e-5f);
    dr_rotate_heading(&st, -1.0f, 0.0f);
    yaw = 2.0f * atan2f(st.q[3], st.q[0]);
    CHECK(fabsf(fabsf(yaw - 1.5707963f * 1.04f) - 3.1415927f) < 1e-5f);
}

static void test_saturation_and_fuzz(void) {
    static const int32_t blocks[] = {1, 2, 3, 16, 4096};
    dr_config cfg;
    dr_state st;
    float out[6];
    int32_t bi, k, i, round;
    dr_config_init(&cfg);
    for (bi = 0; bi < 5; bi++) {
        int32_t b = blocks[bi];
        int32_t count = (MAX_SAMPLES / b) * b;
        CHECK(dr_config_set(&cfg, b, count, 2048.0f, 16.4f, 0.03125f, 0.02f) == DR_OK);
        dr_state_init(&st);
        for (round = 0; round < 3; round++) {
            for (k = 0; k < count; k++) {
                for (i = 0; i < 6; i++) {
                    uint32_t r = rng_next();
                    samples[6 * k + i] = round == 0 ? (int16_t)((r & 1u) ? 32767 : -32768) : (int16_t)(r & 0xffffu);
                }
                dt_us[k] = 3000 + (int32_t)(rng_next() % 4000u);
            }
            CHECK(dr_process(&cfg, &st, scratch, samples, dt_us, count, out, medians) == DR_OK);
            for (i = 0; i < 6; i++) {
                CHECK(out[i] == out[i] && fabsf(out[i]) < 1e30f);
            }
            CHECK(fabsf(st.q[0] * st.q[0] + st.q[1] * st.q[1] + st.q[2] * st.q[2] + st.q[3] * st.q[3] - 1.0f) < 1e-5f);
        }
        CHECK(dr_calibrate(&cfg, &st, samples, count) == DR_MOVED);
    }
}

static void test_calibration(void) {
    dr_config cfg;
    dr_state st;
    int32_t k;
    dr_config_init(&cfg);
    for (k = 0; k < 100; k++) {
        samples[6 * k] = 0;
        samples[6 * k + 1] = 0;
        samples[6 * k + 2] = -16384;
        samples[6 * k + 3] = 10;
        samples[6 * k + 4] = -20;
        samples[6 * k + 5] = 30;
    }
    CHECK(dr_calibrate(&cfg, &st, samples, 100) == DR_OK);
    CHECK(st.q[0] == 0.0f && st.q[1] == 1.0f); /* upside down: 180 degrees about x */
    CHECK(st.gyro_bias_lsb[0] == 10.0f && st.gyro_bias_lsb[1] == -20.0f && st.gyro_bias_lsb[2] == 30.0f);
    CHECK(dr_calibrate(&cfg, &st, samples, 0) == DR_ERR_COUNT);
}

static void test_latlon(void) {
    int32_t lat, lon;
    dr_offset_latlon(473000000, 85000000, 0.0f, 0.0112f, &lat, &lon);
    CHECK(lat == 473000001 && lon == 85000000);
    dr_offset_latlon(0, 1799999990, 100.0f, 0.0f, &lat, &lon);
    CHECK(lon < 0 && lon > -1799999000); /* wrapped across the antimeridian */
    dr_offset_latlon(900000000, 0, 100.0f, 0.0f, &lat, &lon);
    CHECK(lon == 0);
}

int main(void) {
    test_math();
    test_median();
    test_config();
    test_constant_acceleration();
    test_rotation();
    test_saturation_and_fuzz();
    test_calibration();
    test_latlon();
    if (failures) {
        fprintf(stderr, "%d check(s) failed\n", failures);
        return 1;
    }
    printf("kernel C tests passed\n");
    return 0;
}
