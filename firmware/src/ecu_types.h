/*
 * The types every module of the ECU shares: the sample and the step's output (the faces
 * of controller.base), the controller and status codes, the export attribute.
 */
#ifndef ECU_TYPES_H
#define ECU_TYPES_H

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
 * (n_pred = 0 when no plan was made). step_time_s: the whole step, solve_time_s: the
 * QP's update and solve (wall clock, for diagnostics only). */
typedef struct {
  double steer_angle, drive_torque;
  int status, iterations, fallback, observer_reset, n_pred;
  double solve_time_s, cost, slack_max, step_time_s;
  double predicted_pose[ECU_MAX_HORIZON][3];
  double predicted_state[ECU_MAX_HORIZON][3];
} ecu_output_t;

/* The generator inputs' hashes, one "sha256  path" line each (generated). */
ECU_API const char *ecu_version(void);

#endif
