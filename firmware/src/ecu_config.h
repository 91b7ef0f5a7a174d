/*
 * The configuration read from the data file at start-up (ecu_data.c; layout:
 * firmware/tools/ecu_data.py): the tuning of each controller, the longitudinal law, the
 * nominal bicycle and the Koopman model in physical units.
 */
#ifndef ECU_CONFIG_H
#define ECU_CONFIG_H

#include "ecu_build.h"
#include "ecu_types.h"

/* Sum of the encoder's weight counts (layer i: width_i x width_{i-1}, width_{-1} = NX). */
#define ECU_ENCODER_MAX (ECU_NX * ECU_HIDDEN_MAX + (ECU_N_LAYERS) * ECU_HIDDEN_MAX * ECU_HIDDEN_MAX)
#define ECU_NDICT_MAX (ECU_NDICT > 0 ? ECU_NDICT : 1)
/* At least one: an edmdc-linear model has no encoder layers, and C has no zero-size arrays. */
#define ECU_N_LAYERS_MAX (ECU_N_LAYERS > 0 ? ECU_N_LAYERS : 1)

/* One controller's table of controller/tuning.toml (ecu_data.py TUNING_FIELDS). */
typedef struct {
  int n_pred, n_ctrl;
  double q_position, q_yaw, r_steer, p_steer_rate;
  double state_min[3], state_max[3];
  double slack_l1, slack_l2;
  int max_iter;
  double eps_abs, eps_rel;
  double eso_pole, eso_second_pole, disturbance_decay; /* NaN where the table has none */
  double eso_innovation_limit, yaw_rate_bias_pole;     /* NaN where the table has none */
  double slip_target_limit, slip_target_gate;          /* the heading target (every MPC) */
  /* Speed schedule of q_position, q_yaw, r_steer (MpcTuning.weights_at): the low_ weights
   * at vx <= schedule_low, the others at vx >= schedule_high, linear between (m/s). */
  double low_q_position, low_q_yaw, low_r_steer, schedule_low, schedule_high;
  /* The actuator terms (MpcTuning, issue 37; 0: off): the QP's steer-rate rows (rad/s) and
   * the fixed part of the delay the prediction starts after (s). */
  double qp_steer_rate_limit, delay_compensation_s;
  /* Steps per widening of the innovation bound while the innovation keeps its sign beyond
   * it (models.eso.PersistentInnovationBound; 0: a fixed bound; NaN where the table has none). */
  double eso_innovation_persistence;
  /* The widening counts only steps whose measured lateral acceleration |vx r| is below this
   * (m/s^2; 0: every step; NaN where the table has none). */
  double eso_widening_lateral_accel;
  /* Each step of the horizon's pose moves along yaw_i + advance * ts * r_i (MpcTuning,
   * controller/pose_kinematics.py): 0 is eq. 20's explicit Euler, 0.5 the step's midpoint. */
  double pose_heading_advance;
  /* The grip envelope of the yaw-rate rows (MpcTuning, controller/grip_envelope.py,
   * ecu_grip.h): the rear axle's slip beyond its linear need that marks the grip reached
   * (rad; 0: off), the bound's margin over the estimate, the estimate's return once the rear
   * axle grips again (m/s^2 per s) and the memory of the lateral acceleration's peak (s). */
  double grip_slip_excess, grip_margin, grip_recovery, grip_peak_time;
} ecu_tuning_t;

typedef struct {
  double ts;
  double speed_gain, torque_min, torque_max;
  /* Nominal bicycle: Cf, Cr (N/rad per axle), mass (kg), yaw inertia (kg m^2), lf, lr (m). */
  double cf, cr, mass, yaw_inertia, lf, lr;
  /* The grip envelope's rear axle (controller.grip_envelope.RearAxle.nominal: the nominal
   * bicycle's mass, lf, lr, Cr), a record of its own so that a fitted bicycle for LMPC
   * (ecu_data.py --bicycle) leaves it as the Python ECU has it; has_grip_axle 0: not read. */
  double grip_mass, grip_lf, grip_lr, grip_cr;
  int has_grip_axle;
  ecu_tuning_t tuning[ECU_N_CONTROLLERS];
  /* Koopman model in physical units, one A, B, offset per speed knot (ECU_NK = 1: linear);
   * form: ecu_data.py's code (0 linear, 2 scheduled, 3 scheduled with the steer's N). */
  int form;
  double knots[ECU_NK];
  double A[ECU_NK][ECU_NZ][ECU_NZ];
  double B[ECU_NK][ECU_NZ][ECU_NU];
  double offset[ECU_NK][ECU_NZ];
#if ECU_BILINEAR
  /* The steer's bilinear term N per knot (form 3): the steer column of B(z) is B[:, 1] + N z.
   * The torque's N is zero (ecu_data.py refuses another), so only the steer's is stored. */
  double N[ECU_NK][ECU_NZ][ECU_NZ];
#endif
  int state_fields[ECU_NX];      /* index into ecu_sample_t viewed as double[9] */
  int dictionary[ECU_NDICT_MAX]; /* codes of ecu_data.py DICTIONARY_CODES */
  /* Layer l's weights at weight_at[l], input-major: value[weight_at[l] + i * layer_out[l] + o]
   * multiplies input i into output o (the transpose of the file's (out, in) record), so that
   * the lift's sums for neighbouring outputs read neighbouring weights. Where every weight of
   * layer l is a float exactly (weights_single[l]; a float32-trained encoder's are), the layer's
   * storage holds them as floats from single[2 * weight_at[l]] on, in the same order: the same
   * numbers in half the bytes. */
  union {
    double value[ECU_ENCODER_MAX];
    float single[2 * ECU_ENCODER_MAX];
  } weights;
  int weights_single[ECU_N_LAYERS_MAX];
  double biases[ECU_N_LAYERS_MAX * ECU_HIDDEN_MAX];
  int layer_in[ECU_N_LAYERS_MAX], layer_out[ECU_N_LAYERS_MAX];
  int weight_at[ECU_N_LAYERS_MAX], bias_at[ECU_N_LAYERS_MAX];
} ecu_config_t;

/* Read the data file into cfg; 0, or -1 with one line in err. Start-up only: the record
 * being read goes through one static buffer, so two loads may not run at once. */
int ecu_read_data(const char *path, ecu_config_t *cfg, char *err, size_t err_len);

#endif
