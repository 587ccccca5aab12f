/*
 * dr_fused.h: the fused real-time algorithm (board `algorithm: fused`). codegen/kernel/fused.py is the specification.
 *
 * Same front end as the kernel (axis remap, scales, gyro bias, quaternion body -> kernel ENU), plus per sample a
 * Mahony-type tilt correction towards gravity (minus the motion acceleration the GPS showed), the motion's kind
 * (a walker's steps stay below 8 Hz, a vehicle's road and engine shake |f| above it; board key fused_platform),
 * rest detection that an idling engine's shake does not fool (the rate averaged over 0.5 s; never while fixes say
 * the device moves) with, every second at rest, the gyro bias and a tilt/offset filter update, a travel direction
 * turned by the gyro and a speed along it (walking: the learned walking speed, 0 when the steps stop; a vehicle:
 * the integrated along-track acceleration minus its bias, through the kernel's deadband kcfg->deadband_ms2 on its
 * 0.5 s average, and a zero-velocity update that takes back what the speed error gathered when it stops), and at
 * each GPS fix (dr_fused_gps) the heading alignment of the kernel frame to true North, the travel direction, the
 * speed, the along-track accelerometer bias and a 5-state Kalman filter of the gravity leak (tilt error) and the
 * accelerometer's three offsets, fed back into the orientation and the samples. docs/fused.md has the equations.
 *
 * Float32 only, no division, no allocation, no global or static mutable state: the caller owns a dr_config (the
 * kernel's: remap and scales), a dr_fused_config and a dr_fused_state.
 */
#ifndef DR_FUSED_H
#define DR_FUSED_H

#include <stdint.h>

#include "dr_kernel.h"

/* dr_fused_config (the parameters in the form the loop uses), dr_fused_state, the flags DR_FUSED_AT_REST,
 * DR_FUSED_WALKING, DR_FUSED_TURNING and the parameters' order DR_FUSED_P_*: rendered from the declaration
 * (codegen/kernel/layout.py) into dr_layout.h, which dr_kernel.h includes. */

/* Fills cfg from the board constants of dr_board.h. */
void dr_fused_config_init(dr_fused_config *cfg);

/* Sets cfg from DR_FUSED_PARAMS values in the order DR_FUSED_P_* and the units of codegen.kernel.fused.FusedConfig
 * (s, g, m/s^2, degree/s, m/s, gains). Returns DR_OK, or DR_ERR_RANGE (cfg unchanged) when one is outside its limits
 * (dr_fused_params_check). */
int dr_fused_config_set(dr_fused_config *cfg, const float p[DR_FUSED_PARAMS]);

/* Resets st: identity orientation, travel direction East, kernel frame = true ENU, everything else 0
 * (dr_fused_state_start). */
void dr_fused_state_init(dr_fused_state *st);

/* Calibrates st from count >= 1 raw samples at rest (sensor frame, interleaved): tilt and gyro bias as
 * dr_calibrate, the motion statistics started at rest, speed 0. Returns DR_OK, DR_MOVED or DR_ERR_COUNT. */
int dr_fused_calibrate(const dr_config *kcfg, dr_fused_state *st, const int16_t *samples, int32_t count);

/* Copies what a reset should not lose (DR_FUSED_KEPT, from codegen/kernel/layout.py's FUSED.kept: the attitude, the
 * gyro's bias, the accelerometer's offsets and their covariance block, the along-track bias and its variance, the
 * walking speed) into kept, for the caller to keep where a reset leaves it (the ESP32's RTC memory). */
void dr_fused_keep(const dr_fused_state *st, float kept[DR_FUSED_KEPT_LEN]);

/* After a calibration that moved (a board reset on the road): takes up what dr_fused_keep kept before the reset.
 * The tilt/offset filter's tilt part starts again from the attitude (the board may have tilted while it was reset),
 * uncorrelated with the offsets it keeps; the calibration counts as a rest's (cal_moved 0); the speed stays unknown
 * until the next fix. */
void dr_fused_restore(const dr_fused_config *cfg, dr_fused_state *st, const float kept[DR_FUSED_KEPT_LEN]);

/* Processes count >= 1 raw samples (sensor frame, interleaved), each held dt_us[k] microseconds, each through the
 * per-sample steps of docs/fused.md in their order (static inline dr_fused_<step> in dr_fused.c). out: the
 * displacement East, North, Up (m, true ENU; Up 0) over the samples, then the velocity East, North, Up (m/s).
 * Returns DR_OK, DR_ERR_COUNT or DR_ERR_BLOCK (the median option with kcfg->block > DR_FUSED_MEDIAN_MAX): nothing
 * changed. */
int dr_fused_process(const dr_config *kcfg, const dr_fused_config *cfg, dr_fused_state *st, const int16_t *samples,
                     const int32_t *dt_us, int32_t count, float out[6]);

/* One GPS fix's position, called before dr_fused_gps for the same fix: its Doppler velocity (m/s East, North) and its
 * displacement from the previous fix (m East, North; anything for the first). Smooths the receiver's position with
 * its Doppler and the IMU's displacement between fixes (codegen.fused.position_update); afterwards st->fix_ae,
 * fix_an is the smoothed position minus this fix's, where an outage should start from. */
void dr_fused_position(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn, float de, float dn);

/* One GPS fix's Doppler velocity, m/s East and North (0, 0 when the receiver gives no course). */
void dr_fused_gps(const dr_fused_config *cfg, dr_fused_state *st, float ve, float vn);

/* Each Kalman filter's steps, written out by hand (the tests hold them to the matrix forms F P F^T + Q and the Joseph
 * update). Each checks the covariance after it: one gone wrong (a negative variance, a value not finite) is reset to
 * the filter's prior, counted in st->cov_repairs, and the function returns 0; 1 otherwise.
 * The tilt/offset filter (5 states: gravity leak East, North in m/s^2, offsets x, y, z in m/s^2): the process noise
 * over st->kf_t s and st->turn rad; the update with z = d + h b + noise (variance r per axis), x the correction, fed
 * back into the offsets and the attitude. */
int dr_fused_kf_predict(const dr_fused_config *cfg, dr_fused_state *st);
int dr_fused_kf_update(const dr_fused_config *cfg, dr_fused_state *st, float z0, float z1, const float h[2][3],
                       float r, float x[5]);
/* The lateral filter (speed error m/s, lateral leak, folded offsets x, y in m/s^2): F = I + (row 0: f2, f3 in
 * columns 2, 3; s), Q = diag(q_speed, q_leak, 0, 0); the update with z = h . x + noise (variance r), innovation y,
 * x the correction K y (not fed back here). */
int dr_fused_lateral_predict(const dr_fused_config *cfg, dr_fused_state *st, float f2, float f3, float q_speed,
                             float q_leak);
int dr_fused_lateral_correct(const dr_fused_config *cfg, dr_fused_state *st, const float h[4], float r, float y,
                             float x[4]);
/* The position filter (per axis: position, receiver error, m): predict over t s (*phi the error's decay), the
 * update with y = x + e (gain: K, not applied to the estimates here). */
int dr_fused_position_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float *phi);
int dr_fused_position_correct(const dr_fused_config *cfg, dr_fused_state *st, float gain[2]);
/* A vehicle's speed/bias filter (speed m/s, along-track bias m/s^2): predict over t s with F = [[1, -t], [0, 1]],
 * Q = diag(q_speed, q_bias); the update with the fix's speed (variance r), gain: K (not applied here). */
int dr_fused_speed_predict(const dr_fused_config *cfg, dr_fused_state *st, float t, float q_speed, float q_bias);
int dr_fused_speed_correct(const dr_fused_config *cfg, dr_fused_state *st, float r, float gain[2]);

#endif /* DR_FUSED_H */
