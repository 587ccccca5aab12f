/*
 * dr_fused.h: the fused real-time algorithm (board `algorithm: fused`). codegen/kernel/fused.py is the specification.
 *
 * Same front end as the kernel (axis remap, scales, gyro bias, quaternion body -> kernel ENU), plus per sample a
 * Mahony-type tilt correction towards gravity (minus the motion acceleration the GPS showed), rest detection
 * (zero-velocity update, gyro bias re-estimation), a travel direction turned by the gyro and a speed along it
 * (walking: the learned walking speed, 0 when the steps stop; otherwise the integrated along-track acceleration
 * minus its bias, through the kernel's deadband kcfg->deadband_ms2, which also bounds the horizontal acceleration
 * at rest), and at
 * each GPS fix (dr_fused_gps) the heading alignment of the kernel frame to true North, the travel direction, the
 * speed, the along-track accelerometer bias and a 4-state Kalman filter of the gravity leak (tilt error) and the
 * horizontal accelerometer offsets, fed back into the orientation and the samples.
 *
 * Float32 only, no division, no allocation, no global or static mutable state: the caller owns a dr_config (the
 * kernel's: remap and scales), a dr_fused_config and a dr_fused_state.
 */
#ifndef DR_FUSED_H
#define DR_FUSED_H

#include <stdint.h>

#include "dr_kernel.h"

#define DR_FUSED_PARAMS (31) /* floats dr_fused_config_set takes, in the order of codegen.fused.FusedConfig */
#define DR_FUSED_AT_REST (1) /* dr_fused_state.flags bit: the last sample was at rest */
#define DR_FUSED_WALKING (2) /* dr_fused_state.flags bit: the last sample looked like a walker's */
#define DR_FUSED_TURNING (4) /* dr_fused_state.flags bit: the walker was turning */
#define DR_FUSED_MEDIAN_MAX (32) /* longest block (dr_config.block) the median option takes */

/* The parameters, stored in the form the loop uses (every field 4 bytes). */
typedef struct {
    float kp;              /* 1/s, tilt correction gain while fixes arrive */
    float kp_dark;         /* 1/s, the same without GPS */
    float reject_ms2;      /* m/s^2, no tilt correction while | |f_c| - g | exceeds this */
    float steady_ms2;      /* m/s^2, ... or while the GPS acceleration changed more than this between fixes */
    float inv_speed_tau;   /* 1/s, relaxation of a vehicle's speed towards the last GPS speed */
    float gps_timeout_s;   /* s, the GPS counts as lost this long after its last fix */
    float inv_stat_tau;    /* 1/s, motion statistics rate */
    float rest_var;        /* (m/s^2)^2, |f| variance limit for rest */
    float rest_w2;         /* (rad/s)^2, mean squared rate limit for rest */
    float rest_time_s;     /* s, both below their limits this long = at rest */
    float inv_bias_tau;    /* 1/s, gyro bias re-estimation rate at rest */
    float walk_var;        /* (m/s^2)^2, |f| variance above which the device is carried by a walker */
    float min_speed_ms;    /* m/s, GPS speeds below this carry no course */
    float heading_gain;    /* per fix */
    float align_forget;    /* per fix */
    float speed_gain;      /* per fix */
    float bias_gain;       /* per fix, m/s^2 of bias per m/s of speed error per s */
    float walk_speed_gain; /* per fix */
    float kf_bias_var;     /* (m/s^2)^2, initial variance of the horizontal accelerometer offsets (0: no filter) */
    float kf_bias_q;       /* (m/s^2)^2/s, their random walk */
    float kf_tilt_q;       /* (m/s^2)^2/s, random walk of the gravity leak */
    float kf_turn_q;       /* (m/s^2/rad)^2, gravity leak variance per squared radian turned */
    float kf_vel_r;        /* (m/s)^2, twice the GPS velocity variance per axis */
    float kf_align_min;    /* (m/s)^2, heading alignment sums needed before the filter updates */
    float median;          /* > 0: a vehicle's along-track acceleration is the median of the last kcfg->block */
    float pos_var;         /* m^2, the receiver's position error variance per axis (0: no position smoothing) */
    float inv_pos_tau;     /* 1/s, the inverse of its correlation time */
    float pos_step_q;      /* (m/s)^2, variance of the step between fixes (Doppler trapezoid + IMU) per second */
    float hold_rate;       /* 1/s, a walker's slow rotations about Up reach u at this rate (0: at once) */
    float turn_start;      /* rad/s, a walker's turn starts above this smoothed rate about Up */
    float turn_end;        /* rad/s, and ends below this */
} dr_fused_config;

/* The state, field for field codegen.fused.STATE_FIELDS (95 floats). */
typedef struct {
    float q[4];            /* orientation w, x, y, z: body -> kernel ENU */
    float gyro_bias_lsb[3];/* counts */
    float mean_f;          /* m/s^2, mean |f| */
    float var_f;           /* (m/s^2)^2, variance of |f| */
    float w2;              /* (rad/s)^2, mean |omega|^2 */
    float acc_e, acc_n;    /* m/s^2, GPS motion acceleration in the kernel frame */
    float steady;          /* > 0 while that acceleration is steady (steady_ms2^2 - its change^2) */
    float rest_s;          /* s the device has looked at rest */
    float ux, uy;          /* travel direction, kernel frame (unit) */
    float speed;           /* m/s along u */
    float bias;            /* m/s^2, along-track accelerometer bias */
    float walk_speed;      /* m/s */
    float cos_t, sin_t;    /* rotation kernel frame -> true ENU */
    float align_c, align_s;/* (m/s)^2, heading alignment sums */
    float dvx, dvy;        /* m/s, kernel-frame horizontal velocity change since the last fix */
    float since_fix;       /* s since the last GPS update */
    float gps_ve, gps_vn;  /* m/s, the last fix's velocity (true ENU) */
    float gps_speed;       /* m/s, the last fix's speed */
    float gps_ok;          /* > 0 if the last fix had a course (its speed - min_speed_ms) */
    float pe, pn;          /* m, true ENU position accumulated (the caller may reset it) */
    float flags;           /* DR_FUSED_AT_REST | DR_FUSED_WALKING | DR_FUSED_TURNING of the last sample */
    float bax, bay;        /* m/s^2, accelerometer offsets of the body x, y axes (subtracted from every sample) */
    float m[4];            /* s, integral of R(q)'s horizontal rows (r00, r01, r10, r11) since the last fix */
    float turn;            /* rad, integral of |rate about Up| since the last fix */
    float p[10];           /* the tilt/offset filter's covariance, upper triangle row by row (p00 p01 .. p33) */
    float fix_ae, fix_an;  /* m, smoothed position minus the last fix's (true ENU): where an outage starts from */
    float fix_ee, fix_en;  /* m, the receiver's position error estimated at the last fix */
    float fix_pxx, fix_pxe, fix_pee; /* m^2, their covariance (the same for East and North) */
    float dpx, dpy;        /* m, integral of dvx, dvy since the last fix */
    float rate_up;         /* rad/s, the rate about Up smoothed over the motion statistics' time constant */
    float held;            /* rad, rotation about Up a walker's u has not taken yet */
    float med_i, med_n;    /* the median option's ring: next slot, slots filled (whole numbers) */
    float med[DR_FUSED_MEDIAN_MAX]; /* m/s^2, the last along-track accelerations */
} dr_fused_state;

/* Fills cfg from the board constants of dr_board.h. */
void dr_fused_config_init(dr_fused_config *cfg);

/* Sets cfg from DR_FUSED_PARAMS values in the units of codegen.fused.FusedConfig (s, g, m/s^2, degree/s, m/s,
 * gains). Returns DR_OK, or DR_ERR_RANGE (cfg unchanged) when a time constant that must be positive is not. */
int dr_fused_config_set(dr_fused_config *cfg, const float p[DR_FUSED_PARAMS]);

/* Resets st: identity orientation, travel direction East, kernel frame = true ENU, everything else 0. */
void dr_fused_state_init(dr_fused_state *st);

/* Calibrates st from count >= 1 raw samples at rest (sensor frame, interleaved): tilt and gyro bias as
 * dr_calibrate, the motion statistics started at rest, speed 0. Returns DR_OK, DR_MOVED or DR_ERR_COUNT. */
int dr_fused_calibrate(const dr_config *kcfg, dr_fused_state *st, const int16_t *samples, int32_t count);

/* Processes count >= 1 raw samples (sensor frame, interleaved), each held dt_us[k] microseconds. out: the
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

#endif /* DR_FUSED_H */
