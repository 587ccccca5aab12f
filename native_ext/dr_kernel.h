/*
 * dr_kernel.h: the dead-reckoning kernel. One window of raw MPU-6050 samples in, ENU displacement and velocity out.
 *
 * Float32 only, no allocation, no global or static mutable state: the caller owns a dr_config, a dr_state and a
 * scratch area of DR_SCRATCH_FLOATS(block) floats. Their fields are declared in codegen/kernel/layout.py and rendered
 * into dr_layout.h. codegen/kernel/reference.py is the specification; the steps are
 *   1. gyro bias subtraction and scaling to rad/s, accel scaling to m/s^2 (after the board's axis remap);
 *   2. orientation q (body -> ENU) from the gyro: q <- q (x) exp(omega dt / 2), kept at unit length;
 *   3. a = R(q) f - [0, 0, g];
 *   4. per axis, the median of each block of b samples;
 *   5. deadband: |a| < l becomes exactly 0;
 *   6. zero-order hold: over a block of duration T, p += v T + a T^2 / 2 and v += a T (the same as summing the
 *      per-sample steps v_k+1 = v_k + a dt_k, p += v_k dt_k + a dt_k^2 / 2, as a is constant over the block).
 */
#ifndef DR_KERNEL_H
#define DR_KERNEL_H

/* The structs dr_config and dr_state, the return codes DR_OK, DR_MOVED, DR_ERR_*: rendered from the declaration. */
#include "dr_layout.h"

/* Floats of scratch dr_process needs for block size b: one block of ENU accelerations per axis. */
#define DR_SCRATCH_FLOATS(block) (3 * (block))

/* Fills cfg from the board constants of dr_board.h. */
void dr_config_init(dr_config *cfg);

/* Sets cfg's numeric parameters: block b and window n (samples), ranges in counts per g and counts per degree/s,
 * deadband and motion threshold in g. Returns DR_OK, or DR_ERR_BLOCK/DR_ERR_WINDOW/DR_ERR_RANGE (cfg unchanged)
 * for the first outside its limits (dr_params_check). */
int dr_config_set(dr_config *cfg, int32_t block, int32_t window, float accel_lsb_per_g, float gyro_lsb_per_dps,
                  float deadband_g, float motion_threshold_g);

/* Resets st: identity orientation, zero velocity, zero gyro bias. */
void dr_state_init(dr_state *st);

/* Calibrates st from count >= 1 raw samples at rest, interleaved [ax, ay, az, gx, gy, gz] in the sensor frame:
 * tilt from the mean specific force (yaw 0), gyro bias = mean gyro counts, velocity 0.
 * Returns DR_OK, DR_MOVED (st is updated all the same), DR_ERR_COUNT or DR_ERR_RANGE (st unchanged). */
int dr_calibrate(const dr_config *cfg, dr_state *st, const int16_t *samples, int32_t count);

/* Processes count raw samples (a multiple of cfg->block), interleaved [ax, ay, az, gx, gy, gz] in the sensor frame,
 * each held for dt_us[k] microseconds, starting from st's orientation and velocity (both updated).
 * scratch: DR_SCRATCH_FLOATS(cfg->block) floats. out: displacement East, North, Up (m) over the samples, then the
 * velocity East, North, Up (m/s) at their end. medians: NULL, or 3 * count / block floats receiving the block
 * medians after the deadband (m/s^2, block-major: E, N, U of block 0, then block 1, ...).
 * Returns DR_OK, DR_ERR_COUNT or DR_ERR_RANGE (nothing changed). */
int dr_process(const dr_config *cfg, dr_state *st, float *scratch, const int16_t *samples, const int32_t *dt_us,
               int32_t count, float out[6], float *medians);

/* Sets the velocity, m/s East, North, Up. */
void dr_set_velocity(dr_state *st, float ve, float vn, float vu);

/* Turns the earth frame about Up by the angle a with cosine cos_a and sine sin_a (counter-clockwise seen from
 * above; the pair need not be exactly unit): q <- q_up(a) (x) q. The velocity is left as it is. */
void dr_rotate_heading(dr_state *st, float cos_a, float sin_a);

#endif /* DR_KERNEL_H */
