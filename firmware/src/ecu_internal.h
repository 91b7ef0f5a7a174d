/*
 * Internals shared by the core's files: the configuration read from the data file
 * (ecu_data.c) and used by the control law (ecu_core.c, ecu_qp.c).
 */
#ifndef ECU_INTERNAL_H
#define ECU_INTERNAL_H

#include "ecu_build.h"
#include "ecu_core.h"

/* Sum of the encoder's weight counts (layer i: width_i x width_{i-1}, width_{-1} = NX). */
#define ECU_ENCODER_MAX (ECU_NX * ECU_HIDDEN_MAX + (ECU_N_LAYERS) * ECU_HIDDEN_MAX * ECU_HIDDEN_MAX)
#define ECU_NDICT_MAX (ECU_NDICT > 0 ? ECU_NDICT : 1)

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
  /* Speed schedule of q_position, q_yaw, r_steer (MpcTuning.weights_at): the low_ weights
   * at vx <= schedule_low, the others at vx >= schedule_high, linear between (m/s). */
  double low_q_position, low_q_yaw, low_r_steer, schedule_low, schedule_high;
} ecu_tuning_t;

typedef struct {
  double ts;
  double speed_gain, torque_min, torque_max;
  /* Nominal bicycle: Cf, Cr (N/rad per axle), mass (kg), yaw inertia (kg m^2), lf, lr (m). */
  double cf, cr, mass, yaw_inertia, lf, lr;
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
  double weights[ECU_ENCODER_MAX];
  double biases[ECU_N_LAYERS * ECU_HIDDEN_MAX];
  int layer_in[ECU_N_LAYERS], layer_out[ECU_N_LAYERS];
  int weight_at[ECU_N_LAYERS], bias_at[ECU_N_LAYERS];
} ecu_config_t;

/* numpy.searchsorted(s, v, side) on s[0..n-1] (ascending): the first index i with
 * s[i] > v when right != 0 (side="right"), s[i] >= v when right == 0 (side="left"); n when
 * there is none, so v goes in before index i and s stays sorted (ecu_path.c). */
int ecu_search_sorted(const double *s, int n, double v, int right);

/* controller.reference.PathTracker.update (window 2 m behind, 6 m ahead) on a path of
 * n >= 2 points x, y, s (n,) (s increasing): the nearest foot point of (px, py) on the
 * segments around *progress, on all of them when !*has_progress. Sets *progress to the
 * foot point's arc length (m) and *has_progress to 1; returns the signed lateral error (m,
 * > 0 when the point is left of the path). Used by the control core's tracker and by the
 * excitation's own (ecu_path.c). */
double ecu_path_track(const double *x, const double *y, const double *s, int n, double px, double py,
                      double *progress, int *has_progress);

/* Read the data file into cfg; 0, or -1 with one line in err. */
int ecu_read_data(const char *path, ecu_config_t *cfg, char *err, size_t err_len);

/* The steering QP of one controller (ecu_qp.c), a port of controller/steering_qp.py. */
typedef struct {
  int status, iterations;
  double steer[ECU_NC_MAX], slack[3];
  double cost, solve_time_s;
} ecu_qp_solution_t;

/* Select the generated workspace of `controller` and apply the tuning's solver settings. */
int ecu_qp_init(int controller, const ecu_tuning_t *tuning, char *err, size_t err_len);

/* SteeringQp.solve: jac (Np*3 x Nc, row-major), offset (Np*3), gain (Np*3 x Nc, states at
 * steps 1..Np), free (Np*3), warm (Nc); vx (m/s) the measured speed the weights are
 * scheduled on. */
void ecu_qp_solve(double vx, const double *jac, const double *pose_offset, double previous_steer,
                  const double *gain, const double *free_states, const double *warm,
                  ecu_qp_solution_t *solution);

#endif
