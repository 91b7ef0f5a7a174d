/*
 * The ECU's control core: the steering MPCs ESO-DKMPC, DKMPC and LMPC with the
 * longitudinal P controller, the same control step as the Python controllers (the
 * modules of controller/). All of a core's state is one ecu_core_t, the caller's storage
 * (static, or zeroed before the first load: nothing is allocated), so several cores live
 * in one process; each holds one of the generated QP workspaces of its controller
 * (ECU_QP_WORKSPACES per controller, ecu_qp.h) from its load to ecu_core_unload. A loaded
 * core points into itself: it is used where it was loaded, never copied.
 *
 * Life cycle: ecu_core_load (start-up: reads the data file, selects the controller),
 * ecu_core_set_path (start-up or on a path change), then ecu_core_step every Ts = 25 ms;
 * ecu_core_reset forgets plans, progress, the observer and the grip estimate (as
 * Controller.reset()).
 */
#ifndef ECU_CORE_H
#define ECU_CORE_H

#include <stddef.h>

#include "ecu_delay.h"
#include "ecu_grip.h"
#include "ecu_observer.h"
#include "ecu_path_reader.h"
#include "ecu_predict.h"
#include "ecu_qp.h"

typedef struct {
  ecu_config_t cfg;
  int loaded, controller;
  const ecu_tuning_t *tun; /* cfg.tuning[controller] */
  int n_pred, n_ctrl;
  /* Path (ReferencePath arrays) and progress (PathTracker). */
  double path_x[ECU_MAX_PATH_POINTS], path_y[ECU_MAX_PATH_POINTS];
  double path_yaw[ECU_MAX_PATH_POINTS], path_s[ECU_MAX_PATH_POINTS];
  int path_n, has_progress;
  double progress;
  /* SteeringMpc state: last good plan (Nc,), its age, the last command. */
  double plan_steer[ECU_NC_MAX];
  int has_plan, plan_age, has_last;
  double last_steer, last_torque;
  /* The steer commands sent, oldest first (history_n of them, at most ECU_COMMAND_HISTORY):
   * the ones in flight over the delay window (SteeringMpc._command_history). */
  double history[ECU_COMMAND_HISTORY];
  int history_n;
  /* Delay compensation of this step (QpSteeringMpc._prepare): the prediction was made from
   * the measured sample and moved over the window; make_plan uses it as it is. */
  int prepared;
  ecu_prediction_basis_t basis;
  double sample_age_s; /* the age of the sample being stepped (ecu_core_step_aged) */
  /* The grip envelope (QpSteeringMpc.grip) and the yaw-rate bound of this step's QP
   * (rad/s; INFINITY: the table's bounds), from the measured sample in prepare. */
  ecu_grip_t grip;
  double yaw_rate_bound;
  /* ESO-DKMPC: the observers; the step's local model and z_k (for the observer's update). */
  ecu_observer_t observer;
  ecu_local_model_t model;
  double lifted[ECU_NZ];
  double decay_power[ECU_NP_MAX]; /* disturbance_decay^i, i = 0..Np-1 (set at load: pow once) */
  ecu_qp_t qp;
  /* One step's working arrays (no state between steps): the horizon's reference poses,
   * free (Np + 1, 3), gain (Np + 1, 3, Nc), nominal states, poses, their Jacobian. */
  double reference[ECU_NP_MAX][3];
  double free[ECU_NP_MAX + 1][3], gain[ECU_NP_MAX + 1][3][ECU_NC_MAX], nominal_states[ECU_NP_MAX + 1][3];
  double poses[ECU_NP_MAX][3], jac[ECU_NP_MAX][3][ECU_NC_MAX], pose_offset[ECU_NP_MAX][3];
} ecu_core_t;

/* sizeof(ecu_core_t), for callers that allocate a core themselves (ctypes). */
ECU_API size_t ecu_core_size(void);

/* Start-up: read the data file (firmware/tools/ecu_data.py) and select controller
 * "eso-dkmpc", "dkmpc" or "lmpc". 0 on success; otherwise -1 and one line in err
 * (the file, the record, and for a shape mismatch the file's and the build's shapes). */
ECU_API int ecu_core_load(ecu_core_t *core, const char *data_path, const char *controller, char *err,
                          size_t err_len);

/* Give the core's QP workspace back (the core steps no more until loaded again). */
ECU_API void ecu_core_unload(ecu_core_t *core);

/* Set the path: n points x, y (m), yaw (rad, unwrapped) and s (m, arc length from 0), as
 * controller.reference.ReferencePath holds them. Resets the progress. 0 or -1 + err. */
ECU_API int ecu_core_set_path(ecu_core_t *core, const double *x, const double *y, const double *yaw,
                              const double *s, int n, char *err, size_t err_len);

/* ecu_core_set_path with the pool's path PATH_ID. 0 or -1 + err. */
int ecu_core_select_path(ecu_core_t *core, const ecu_path_pool_t *paths, int path_id, char *err, size_t err_len);

/* Copy the current path (at most max points) out; returns its number of points. */
ECU_API int ecu_core_path_copy(const ecu_core_t *core, double *x, double *y, double *yaw, double *s, int max);

/* Forget plans, the previous command, progress, the observer and the grip estimate
 * (Controller.reset). */
ECU_API void ecu_core_reset(ecu_core_t *core);

/* One control step (Controller.step): never fails; the command is finite and within
 * the limits whatever the sample. */
ECU_API void ecu_core_step(ecu_core_t *core, const ecu_sample_t *sample, ecu_output_t *out);

/* ecu_core_step on a sample that was sample_age_s old when the task started (s; the caller
 * computes it from its clock: the control law takes it as data, VehicleSample.sample_age_s).
 * Only the delay compensation reads it (delay_compensation_s > 0); ecu_core_step is this
 * with age 0. */
ECU_API void ecu_core_step_aged(ecu_core_t *core, const ecu_sample_t *sample, double sample_age_s,
                                ecu_output_t *out);

/* The build's shapes, one line (generated header ecu_build.h). */
ECU_API const char *ecu_build_shapes(void);

#endif
