/*
 * bench_fused.c: a harness for instruction counting (valgrind --tool=callgrind) by benchmarks/fused.py:
 * `bench_fused W` runs W windows of DR_WINDOW_SAMPLES pseudo-random samples through dr_fused_process, with a GPS
 * update after each window; the difference between two runs with different W gives the instructions per window.
 */
#include <stdio.h>
#include <stdlib.h>

#include "dr_board.h"
#include "dr_fused.h"

static int16_t samples[6 * DR_WINDOW_SAMPLES];
static int32_t dt_us[DR_WINDOW_SAMPLES];

int main(int argc, char **argv) {
    dr_config kcfg;
    dr_fused_config cfg;
    dr_fused_state st;
    float out[6];
    uint32_t r = 1u;
    int32_t k, i, w, windows = argc > 1 ? atoi(argv[1]) : 1;
    dr_config_init(&kcfg);
    dr_fused_config_init(&cfg);
    dr_fused_state_init(&st);
    for (k = 0; k < DR_WINDOW_SAMPLES; k++) {
        for (i = 0; i < 6; i++) {
            r = r * 1664525u + 1013904223u;
            samples[6 * k + i] = (int16_t)((int32_t)(r >> 22) - 512 + (i == 2 ? 16384 : 0));
        }
        dt_us[k] = 4900 + (int32_t)((r >> 8) % 200u);
    }
    for (w = 0; w < windows; w++) {
        if (dr_fused_process(&kcfg, &cfg, &st, samples, dt_us, DR_WINDOW_SAMPLES, out) != DR_OK) {
            return 1;
        }
        dr_fused_position(&cfg, &st, 1.0f, 0.5f, 1.0f, 0.5f);
        dr_fused_gps(&cfg, &st, 1.0f, 0.5f);
    }
    printf("%g %g %g\n", (double)out[0], (double)out[1], (double)out[2]);
    return 0;
}
