/*
 * dr_eskf.h: the error-state Kalman filter for a vehicle (23 error states), float32, the C port of
 * codegen/kernel/eskf.py (the float64 specification; docs/eskf.md has the equations).
 *
 * The caller owns a dr_config (the board's axis map and scales, dr_kernel.h), a dr_eskf_config and a
 * dr_eskf_state; nothing is allocated, nothing static is written. The error state's order is DR_ESKF_ERR_*; the
 * covariance is the full symmetric matrix p[DR_ESKF_N][DR_ESKF_N] (2.1 KB), indexed by those names.
 *
 *   dr_eskf_config_init(&cfg); dr_eskf_state_init(&st);
 *   dr_eskf_calibrate(&kcfg, &cfg, &st, rest_samples, n);             the tilt and biases
 *   dr_eskf_process(&kcfg, &cfg, &st, samples, dt_us, n, out);         the strapdown step, the covariance, NHC/ZUPT
 *   dr_eskf_gps(&cfg, &st, t_s, e, n, u, ve, vn);                      a fix: the yaw alignment, then updates
 */
#ifndef DR_ESKF_H
#define DR_ESKF_H

#include <stdint.h>

#include "dr_kernel.h"

/* The error state: 23 values in this order (codegen.kernel.eskf's ERR_*). */
#define DR_ESKF_N (23)
#define DR_ESKF_ERR_P (0)   /* position E N U, m */
#define DR_ESKF_ERR_V (3)   /* velocity E N U, m/s */
#define DR_ESKF_ERR_TH (6)  /* attitude, a small rotation in ENU, rad */
#define DR_ESKF_ERR_BG (9)  /* gyro bias, body, rad/s */
#define DR_ESKF_ERR_BA (12) /* accelerometer bias, body, m/s^2 */
#define DR_ESKF_ERR_MU (15) /* the mounting's pitch and yaw, rad */
#define DR_ESKF_ERR_SG (17) /* the gyro's turn-rate error per rad/s about Up, body, 1 */
#define DR_ESKF_ERR_GE (20) /* the receiver's position error E N U, m */

/* The yaw fit's sums, al_sums[] (codegen.kernel.eskf._alignment_sums; du the wander frame's velocity change over a
 * fix interval, s the integral of the body's heading over it, dv the GPS's velocity change; complex as E + i N). */
#define DR_ESKF_AL_N (0)      /* intervals */
#define DR_ESKF_AL_DD (1)     /* |du|^2 */
#define DR_ESKF_AL_SS (2)     /* |s|^2 */
#define DR_ESKF_AL_DS (3)     /* conj(du) s: real, imaginary */
#define DR_ESKF_AL_DV (5)     /* conj(du) dv */
#define DR_ESKF_AL_SV (7)     /* conj(s) dv */
#define DR_ESKF_AL_VV (9)     /* |dv|^2 */
#define DR_ESKF_AL_SUMS (10)

/* The steps the observer hook sees (the host's tests; nothing on the device). */
#define DR_ESKF_STEP_PRIOR (0)
#define DR_ESKF_STEP_PREDICT (1)
#define DR_ESKF_STEP_UPDATE (2)

/* dr_eskf_process's return codes. */
#define DR_ESKF_OK (0)
#define DR_ESKF_ERR_COUNT (-1)

/* The filter's parameters (codegen.kernel.eskf.EskfConfig, the same names and units). */
typedef struct {
    float cov_dt_s;              /* s between covariance propagations */
    float nhc_dt_s;              /* s between pseudo-measurements */
    float accel_noise;           /* m/s^2/sqrt(Hz) */
    float gyro_noise;            /* rad/s/sqrt(Hz) */
    float accel_bias_walk;       /* m/s^2/sqrt(s) */
    float gyro_bias_walk;        /* rad/s/sqrt(s) */
    float mount_walk;            /* rad/sqrt(s) */
    float turn_scale_walk;       /* 1/sqrt(s) */
    float gps_pos_sigma;         /* m, per horizontal axis */
    float gps_up_sigma;          /* m */
    float gps_tau_s;             /* s */
    float gps_white_sigma;       /* m */
    float gps_vel_sigma;         /* m/s */
    float gps_slow_sigma;        /* m/s */
    float nhc_sigma;             /* m/s */
    float saturation_excess_ms2; /* m/s^2 */
    float nhc_lever_m;           /* m */
    float nhc_gate;              /* sigmas */
    float nhc_min_speed;         /* m/s */
    float zupt_sigma;            /* m/s */
    float zupt_gate;             /* normalised square, 1 */
    float zaru_sigma;            /* rad/s */
    float rest_accel_g;          /* g */
    float rest_gyro_dps;         /* deg/s */
    float rest_time_s;           /* s */
    float rest_speed_ms;         /* m/s */
    float rest_horizontal_ms2;   /* m/s^2 */
    float stat_tau_s;            /* s */
    float align_fixes;           /* fix intervals */
    float align_yaw_sigma_deg;   /* deg */
    float align_scale;           /* 1 */
    float align_speed_ms;        /* m/s */
    float init_yaw_sigma_deg;    /* deg */
    float init_tilt_sigma_deg;   /* deg */
    float init_tilt_moving_deg;  /* deg */
    float init_gyro_bias_dps;    /* deg/s */
    float init_gyro_bias_moving_dps; /* deg/s */
    float init_accel_bias_ms2;   /* m/s^2 */
    float init_mount_sigma_deg;  /* deg */
    float init_turn_scale;       /* 1 */
} dr_eskf_config;

/* The whole state (codegen.kernel.eskf.EskfState). */
typedef struct {
    float pos[3];                  /* m, ENU */
    float vel[3];                  /* m/s, ENU */
    float q[4];                    /* attitude w x y z, body -> ENU */
    float bg[3];                   /* rad/s, body */
    float ba[3];                   /* m/s^2, body */
    float sg[3];                   /* 1, body */
    float ge[3];                   /* m, ENU */
    float mount[3][3];             /* body -> vehicle (x forward, y left, z up) */
    float acc_a[3][3];             /* s: sum of R dt since the last propagation */
    float acc_b[3][3];             /* rad: sum of R turn dt */
    float acc_dv[3];               /* m/s: sum of R f dt */
    float acc_t;                   /* s: the interval */
    float sat_dv;                  /* m/s: what clipped samples may have lost in it */
    float since_nhc;               /* s since the last pseudo-measurement */
    float mean_f;                  /* m/s^2: |f| smoothed */
    float var_f;                   /* (m/s^2)^2: its variance */
    float ws[3];                   /* rad/s: the rate smoothed */
    float ah[2];                   /* m/s^2: the horizontal specific force smoothed */
    float rest_s;                  /* s at rest so far */
    float rate2;                   /* (rad/s)^2: the last sample's rate squared */
    float gps_speed;               /* m/s: the last fix's */
    float t_fix;                   /* s: the last fix's time */
    float al_du[2];                /* m/s: the wander frame's velocity change since the last fix */
    float al_u[2];                 /* 1: the body's heading in the wander frame since the calibration, E + i N */
    float al_s[2];                 /* s: its integral since the last fix */
    float al_sums[DR_ESKF_AL_SUMS]; /* the yaw fit's sums (DR_ESKF_AL_*) */
    float al_prev[2];              /* m/s: the previous fix's velocity */
    float al_have_prev;            /* 1 once a fix was seen */
    float aligned;                 /* 1 once the filter runs */
    float gyro_moving;             /* 1 if calibration saw motion */
    float cov_repairs;             /* covariances that went wrong and were reset */
    /* the error state's covariance, symmetric; last, so that the fields above sit within the ESP32's load/store
     * offsets from the struct's address (0-1020 bytes: one instruction per access instead of three) */
    float p[DR_ESKF_N][DR_ESKF_N];
} dr_eskf_state;

/* Fills cfg with codegen.kernel.eskf.EskfConfig's defaults. */
void dr_eskf_config_init(dr_eskf_config *cfg);

/* Resets st: identity attitude, everything else 0, the filter not started. */
void dr_eskf_state_init(dr_eskf_state *st);

/* Calibration from count >= 1 raw samples (sensor frame, interleaved [ax ay az gx gy gz]): the tilt (yaw 0), the
 * gyro bias and the accelerometer bias along the mean specific force (its length less g) from their mean. Returns 1
 * if the device moved during it (the kernel's motion limit), 0 if not, DR_ESKF_ERR_COUNT (st unchanged) for no
 * samples or no gravity. */
int dr_eskf_calibrate(const dr_config *kcfg, const dr_eskf_config *cfg, dr_eskf_state *st, const int16_t *samples,
                      int32_t count);

/* The fix interval that spans a calibration: ve, vn (m/s) the GPS velocity of a fix `seconds` before the
 * calibration's end (call it after dr_eskf_calibrate; the next dr_eskf_gps closes the interval). Over the calibration
 * the wander frame's velocity change is 0 by construction, so that interval's GPS velocity change is the mean
 * acceleration a calibration in motion took for gravity: it ties the yaw to the offset that acceleration leaves. */
void dr_eskf_calibration_interval(dr_eskf_state *st, float ve, float vn, float seconds);

/* The strapdown step over count raw samples (sensor frame), each held dt_us[k] us, with the covariance propagated
 * every cov_dt_s and the pseudo-measurements every nhc_dt_s. out: position E N U (m), velocity E N U (m/s) after
 * them. Returns DR_ESKF_OK or DR_ESKF_ERR_COUNT (count < 0). */
int dr_eskf_process(const dr_config *kcfg, const dr_eskf_config *cfg, dr_eskf_state *st, const int16_t *samples,
                    const int32_t *dt_us, int32_t count, float out[6]);

/* A GPS fix at t_s (s), position e, n, u (m, the run's ENU) and horizontal velocity ve, vn (m/s): before the filter
 * runs, the yaw alignment (returns 1 if the filter started now); after, the fix's five updates (returns 0). */
int dr_eskf_gps(const dr_eskf_config *cfg, dr_eskf_state *st, float t_s, float e, float n, float u, float ve,
                float vn);

/* The steps, for the host's tests against the reference's matrix forms. */
/* P <- Phi P Phi^T + Q over the accumulated interval (no check). */
void dr_eskf_propagate_covariance(const dr_eskf_config *cfg, dr_eskf_state *st);
/* One scalar update of p and dx with the row h (nnz entries h_value at h_index), residual y and variance r.
 * Returns 1, or 0 (nothing changed) if the innovation's variance is not positive. */
int dr_eskf_scalar_update(float p[DR_ESKF_N][DR_ESKF_N], float dx[DR_ESKF_N], const int32_t *h_index,
                          const float *h_value, int32_t nnz, float y, float r);
/* The non-holonomic constraint's two rows (dense, lateral then vertical) and predicted values (m/s). */
void dr_eskf_nhc_rows(const dr_eskf_state *st, float h[2][DR_ESKF_N], float predicted[2]);
/* Whether the covariance is usable: every entry a bounded number, symmetric, variances >= 0 and every
 * correlation within 1 (to rounding). */
int dr_eskf_covariance_usable(const float p[DR_ESKF_N][DR_ESKF_N]);
/* The start covariance (from st's attitude and calibration). */
void dr_eskf_prior(const dr_eskf_config *cfg, dr_eskf_state *st);

#endif /* DR_ESKF_H */
