/*
 * eskf_harness.c: drives the error-state filter's C (dr_eskf.c, compiled for the ESP32 by the LLVM route with the
 * natmod's flags and linked with this file by mpy_ld) on qemu-system-xtensa; codegen/natmod/xtensa_eskf.py builds
 * and runs it. The filter is not in dr_native.mpy yet, so it is linked here directly; the instructions counted are
 * the filter's own, as in harness.c.
 *
 *   magic "DRE1" | steps | workspace | output | cov_dt_s | nhc_dt_s (floats; 0: the default) | steps: kind ('C', 'P', 'G') | samples n | payload
 *   C: int16 samples[6n]   P: int16 samples[6n], int32 dt_us[n]   G: float t e n u ve vn (n = 6) (sim_steps.h)
 *   one step alone, on the state as it is (n = 0; the state is saved before and restored after, so the run goes on
 *   unchanged): Q the covariance propagation, K the covariance check, U one scalar update with the constraint's
 *   lateral row (8 non-zeros), N the constraint's rows
 * Every step writes: instructions (ICOUNT), return code, position E N U, velocity E N U, repairs, started.
 * Returns the output's size in bytes.
 */
#include <stddef.h>
#include <stdint.h>

#include "dr_eskf.h"
#include "dr_kernel.h"
#include "sim_steps.h"

#define HARNESS_MAGIC (0x31455244u) /* "DRE1" */
#define HEADER_WORDS (8)
#define RECORD_FLOATS (8)

typedef struct {
    dr_config kcfg;
    dr_eskf_config cfg;
    dr_eskf_state st;
    dr_eskf_state saved;
    float out[6];
    float dx[DR_ESKF_N];
    float h[2][DR_ESKF_N];
    float predicted[2];
    int32_t h_index[DR_ESKF_N];
    float h_value[DR_ESKF_N];
} workspace;

/* *to = *from by floats (a struct assignment may become a memcpy call, which nothing here links). */
static void copy_state(dr_eskf_state *to, const dr_eskf_state *from) {
    float *t = (float *)to;
    const float *f = (const float *)from;
    uint32_t i;
    for (i = 0; i < sizeof(dr_eskf_state) / sizeof(float); i++) {
        t[i] = f[i];
    }
}

/* One step alone on a copy of the state (the caller restores it); returns its code. */
static int32_t alone(workspace *w, uint32_t kind) {
    int32_t code = 0, nnz = 0, i;
    if (kind == 'Q') {
        dr_eskf_propagate_covariance(&w->cfg, &w->st);
    } else if (kind == 'K') {
        code = dr_eskf_covariance_usable((const float(*)[DR_ESKF_N])w->st.p);
    } else if (kind == 'N') {
        dr_eskf_nhc_rows(&w->st, w->h, w->predicted);
    } else {
        dr_eskf_nhc_rows(&w->st, w->h, w->predicted);
        for (i = 0; i < DR_ESKF_N; i++) {
            w->dx[i] = 0.0f;
            if (w->h[0][i] != 0.0f) {
                w->h_index[nnz] = i;
                w->h_value[nnz] = w->h[0][i];
                nnz++;
            }
        }
        code = dr_eskf_scalar_update(w->st.p, w->dx, w->h_index, w->h_value, nnz, 0.1f, 0.04f);
    }
    return code;
}

uint32_t mpy_init(const uint32_t *input) {
    workspace *w = (workspace *)input[2];
    uint32_t *at = (uint32_t *)input[3];
    uint32_t *start = at;
    const uint32_t *step = input + HEADER_WORDS;
    uint32_t steps = input[1], k, i, t0 = 0, t1 = 0;
    if (input[0] != HARNESS_MAGIC) {
        return 0;
    }
    dr_config_init(&w->kcfg);
    dr_eskf_config_init(&w->cfg);
    if (((const float *)input)[4] > 0.0f) {
        w->cfg.cov_dt_s = ((const float *)input)[4];
    }
    if (((const float *)input)[5] > 0.0f) {
        w->cfg.nhc_dt_s = ((const float *)input)[5];
    }
    dr_eskf_state_init(&w->st);
    for (k = 0; k < steps; k++) {
        sim_step s;
        int32_t code = 0;
        step = sim_step_read(step, &s);
        if (s.kind == 'C') {
            t0 = sim_instructions();
            code = dr_eskf_calibrate(&w->kcfg, &w->cfg, &w->st, s.samples, (int32_t)s.n);
            t1 = sim_instructions();
        } else if (s.kind == 'P') {
            t0 = sim_instructions();
            code = dr_eskf_process(&w->kcfg, &w->cfg, &w->st, s.samples, s.dt_us, (int32_t)s.n, w->out);
            t1 = sim_instructions();
        } else if (s.kind != 'G') {
            copy_state(&w->saved, &w->st);
            t0 = sim_instructions();
            code = alone(w, s.kind); /* U includes the rows' set-up: N alone says how much of it that is */
            t1 = sim_instructions();
            copy_state(&w->st, &w->saved);
        } else {
            const float *g = s.values;
            t0 = sim_instructions();
            code = dr_eskf_gps(&w->cfg, &w->st, g[0], g[1], g[2], g[3], g[4], g[5]);
            t1 = sim_instructions();
        }
        *at++ = t1 - t0;
        *at++ = (uint32_t)code;
        for (i = 0; i < 3; i++) {
            ((float *)at)[i] = w->st.pos[i];
            ((float *)at)[3 + i] = w->st.vel[i];
        }
        ((float *)at)[6] = w->st.cov_repairs;
        ((float *)at)[7] = w->st.aligned;
        at += RECORD_FLOATS;
    }
    return (uint32_t)((at - start) * sizeof(uint32_t));
}
