/*
 * The ECU's control core (libecu.so): the steering MPCs ESO-DKMPC, DKMPC and LMPC with
 * the longitudinal P controller, the same control step as the Python controllers
 * (the modules of controller/). One core per process; all storage is static (no heap).
 *
 * Life cycle: ecu_load (start-up: reads the data file, selects the controller),
 * ecu_set_path (start-up or on a path change), then ecu_step every Ts = 25 ms;
 * ecu_reset forgets plans, progress and the observer (as Controller.reset()).
 */
#ifndef ECU_CORE_H
#define ECU_CORE_H

#include <stddef.h>

/* The library exports these functions only (built with -fvisibility=hidden): the OSQP
 * sources inside keep their symbols to themselves, so a process that also loads the
 * Python osqp extension never mixes the two. */
#define ECU_API __attribute__((visibility("default")))

/* Controller ids, in the order of firmware/tools/ecu_data.py QP_CONTROLLERS. */
enum ecu_controller { ECU_ESO_DKMPC = 0, ECU_DKMPC = 1, ECU_LMPC = 2, ECU_N_CONTROLLERS = 3 };

/* Solver outcome; the values of controller.base.SolverStatus and CTRL_DIAG.QP_STATUS. */
enum ecu_status {
  ECU_SOLVED = 0, ECU_SOLVED_INACCURATE = 1, ECU_MAX_ITERATIONS = 2, ECU_INFEASIBLE = 3,
  ECU_NUMERICAL_ERROR = 4, ECU_NOT_RUN = 15
};

/* Largest horizon of any build (the step result's arrays). */
#define ECU_MAX_HORIZON 200
/* Largest path (the contract's limit, revision 2). */
#define ECU_MAX_PATH_POINTS 100000

/* controller.base.VehicleSample, field for field (SI units, rad). */
typedef struct {
  double vx, vy, yaw_rate, x, y, yaw, steer_angle, drive_torque, target_speed;
} ecu_sample_t;

/* controller.base.Command plus StepDebug. predicted_* rows 0..n_pred-1 are steps 1..Np
 * (n_pred = 0 when no plan was made). step_time_s: the whole ecu_step, solve_time_s: the
 * QP's update and solve (wall clock, for diagnostics only). */
typedef struct {
  double steer_angle, drive_torque;
  int status, iterations, fallback, observer_reset, n_pred;
  double solve_time_s, cost, slack_max, step_time_s;
  double predicted_pose[ECU_MAX_HORIZON][3];
  double predicted_state[ECU_MAX_HORIZON][3];
} ecu_output_t;

/* Start-up: read the data file (firmware/tools/ecu_data.py) and select controller
 * "eso-dkmpc", "dkmpc" or "lmpc". 0 on success; otherwise -1 and one line in err
 * (the file, the record, and for a shape mismatch the file's and the build's shapes). */
ECU_API int ecu_load(const char *data_path, const char *controller, char *err, size_t err_len);

/* Set the path: n points x, y (m), yaw (rad, unwrapped) and s (m, arc length from 0), as
 * controller.reference.ReferencePath holds them. Resets the progress. 0 or -1 + err. */
ECU_API int ecu_set_path(const double *x, const double *y, const double *yaw, const double *s, int n,
                 char *err, size_t err_len);

/* Read and check a path CSV as controller.reference.ReferencePath.from_csv does (the
 * contract's checks, the same messages), then ecu_set_path. 0 or -1 + err. */
ECU_API int ecu_load_path_csv(const char *file, char *err, size_t err_len);

/* The ECU's paths by PATH_ID (all together at most ECU_MAX_PATH_POINTS points): forget
 * them, read and check one more, whether one is loaded, make one the core's path. */
void ecu_path_pool_reset(void);
int ecu_path_pool_add(int path_id, const char *file, char *err, size_t err_len);
int ecu_path_pool_has(int path_id);
int ecu_path_pool_select(int path_id, char *err, size_t err_len);

/* Copy the current path (at most max points) out; returns its number of points. */
ECU_API int ecu_path_copy(double *x, double *y, double *yaw, double *s, int max);

/* Forget plans, the previous command, progress and the observer (Controller.reset). */
ECU_API void ecu_reset(void);

/* One control step (Controller.step): never fails; the command is finite and within
 * the limits whatever the sample. */
ECU_API void ecu_step(const ecu_sample_t *sample, ecu_output_t *out);

/* The generator inputs' hashes, one "sha256  path" line each (generated). */
ECU_API const char *ecu_version(void);

/* The build's shapes, one line (generated header ecu_build.h). */
ECU_API const char *ecu_build_shapes(void);

#endif
