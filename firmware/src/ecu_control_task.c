/*
 * The control task (see ecu_control_task.h); names follow firmware_sim/control_task.py.
 */
#include <math.h>
#include <stdio.h>

#include "ecu_control_task.h"
#include "ecu_dead_reckoning.h"
#include "ecu_modes.h"
#include "os.h"

typedef struct {
  double steer, torque, solve_time_s;
  int qp_status, iterations, faults;
} request_t;

static double wall_seconds(void) { return 1e-9 * (double)os_monotonic_ns(); }

/* The request of the mode: CMD_VALID = 0 holds, SAFE_STOP brakes, ACTIVE / DEGRADED run
 * the law (a new engagement or path resets the core and selects the path first). */
static request_t make_request(ecu_node_t *node, int previous_mode, const ecu_events_t *e, int64_t sample_age,
                              int64_t now_ns) {
  const ecu_rx_state_t *rx = &node->rx;
  request_t r = {node->previous_valid_steer, 0.0, 0.0, ECU_NOT_RUN, 0, 0};
  char err[256];
  if (node->mode == ECU_SAFE_STOP) {
    ecu_safe_stop_command(node->previous_valid_steer, e->standstill, &r.steer, &r.torque);
    return r;
  }
  if (node->mode != ECU_ACTIVE && node->mode != ECU_DEGRADED) return r; /* CMD_VALID = 0: hold, no torque */
  if ((previous_mode != ECU_ACTIVE && previous_mode != ECU_DEGRADED) || node->active_path_id != rx->planner_path_id) {
    r.faults |= ECU_MODEL_RESET;
    ecu_core_reset(node->core);
    if (ecu_core_select_path(node->core, node->paths, rx->planner_path_id, err, sizeof err) != 0) {
      node->active_path_id = -1;
      fprintf(stderr, "error: set_path(PATH_ID %d) failed: %s\n", rx->planner_path_id, err);
      r.steer = r.torque = NAN;
      return r;
    }
    node->active_path_id = rx->planner_path_id;
    ecu_excite_reset(node->excite, node->active_path_id); /* a new engagement: the program starts again */
  }
  const ecu_measurement_t *m = &rx->sample;
  ecu_sample_t sample = {m->vx, m->vy, m->yaw_rate, m->x, m->y, m->yaw, m->steer_angle, m->drive_torque,
                         rx->planner_speed};
  /* The sample's age at the task start (s), as data for the delay compensation
   * (VehicleSample.sample_age_s); in DEGRADED dead reckoning moved the sample to the task
   * start, so it is then 0. */
  double age_s = (double)sample_age / 1e9;
  if (node->mode == ECU_DEGRADED) {
    if (ecu_dead_reckoning(&sample, age_s) != 0) {
      r.steer = r.torque = NAN;
      return r;
    }
    age_s = 0.0;
  }
  ecu_output_t *out = &node->out;
  ecu_core_step_aged(node->core, &sample, age_s, out);
  if (out->fallback) r.faults |= ECU_SOLVER_FALLBACK;
  if (out->observer_reset) r.faults |= ECU_MODEL_RESET;
  r.steer = out->steer_angle;
  r.torque = out->drive_torque;
  /* --excite: the identification excitation on the law's command (ACTIVE only) */
  ecu_excite_step(node->excite, node->paths, (double)now_ns / 1e9, node->mode == ECU_ACTIVE, m->vx, m->x, m->y,
                  &r.steer, &r.torque, -STEER_LIMIT, STEER_LIMIT, -TORQUE_LIMIT, TORQUE_LIMIT);
  r.qp_status = out->status;
  r.iterations = out->iterations;
  r.solve_time_s = out->solve_time_s;
  return r;
}

static void record_timing(ecu_node_t *node, double release_jitter_s, double task_time_s, double solve_time_s,
                          int64_t now_ns, ecu_when_t tx) {
  const ecu_rx_state_t *rx = &node->rx;
  double input_age = NAN, latency = NAN;
  if (node->realtime && rx->has_sample && rx->sample_arrival.set && tx.set) {
    input_age = (double)(now_ns - rx->sample_arrival.ns) / 1e9;
    latency = (double)(tx.ns - rx->sample_arrival.ns) / 1e9;
  }
  const double row[ECU_TIMING_FIELDS] = {release_jitter_s, task_time_s, solve_time_s, input_age, latency,
                                         (double)node->overruns};
  ecu_timing_record(&node->timing, row, now_ns, node->mode);
}

void ecu_control_task(ecu_node_t *node, int64_t now_ns, double release_jitter_s, double started_s) {
  ecu_rx_state_t *rx = &node->rx;
  ecu_events_t e;
  node->cycles++;
  int has_age = rx->has_sample && rx->sample_arrival.set;
  int64_t age = has_age ? now_ns - rx->sample_arrival.ns : 0;
  e.load_failed = node->load_error != NULL;
  e.sample_seen = rx->sample_seen;
  e.sample_fresh = has_age && age <= SAMPLE_STALE_MS * NS_PER_MS;
  e.sample_lost = !has_age || age > SAMPLE_LOST_MS * NS_PER_MS || rx->reference_restarted;
  e.planner_ok = rx->has_planner && rx->planner_arrival.set &&
                 now_ns - rx->planner_arrival.ns <= PLANNER_TIMEOUT_MS * NS_PER_MS;
  if (node->awaiting_disengage && rx->planner_disengaged_seen) node->awaiting_disengage = 0;
  e.standstill = e.sample_fresh && rx->has_sample && fabs(rx->sample.vx) < STANDSTILL_SPEED;
  e.engage = rx->has_planner && rx->planner_engage;
  e.path_known = rx->has_planner && ecu_paths_has(node->paths, rx->planner_path_id);
  e.rearmed = !node->awaiting_disengage;
  e.controller_failed = node->fallback_streak >= CONTROLLER_FAILED_CYCLES;
  int previous_mode = node->mode;
  node->mode = ecu_mode_transition(previous_mode, &e);
  if (node->mode != previous_mode && node->mode == ECU_SAFE_STOP) {
    node->awaiting_disengage = 1;
    rx->planner_disengaged_seen = 0;
  }
  /* FAULTS bits 0 and 1 of this cycle, then the next cycle's RX flags start. */
  int faults = 0, unknown_path = rx->has_planner && !e.path_known;
  if (!e.sample_fresh || rx->torn || rx->stale || rx->implausible || !e.planner_ok || unknown_path)
    faults |= ECU_INPUT_TIMEOUT;
  if (rx->e2e_error) faults |= ECU_E2E_ERROR;
  rx->e2e_error = rx->torn = rx->stale = rx->implausible = rx->reference_restarted = 0;
  if (node->pending_model_reset) {
    faults |= ECU_MODEL_RESET;
    node->pending_model_reset = 0;
  }
  request_t r = make_request(node, previous_mode, &e, age, now_ns);
  faults |= r.faults;
  double steer = r.steer, torque = r.torque;
  if (ecu_guard_command(&steer, &torque, node->previous_valid_steer)) faults |= ECU_SOLVER_FALLBACK;
  node->previous_valid_steer = steer;
  int mode = node->mode;
  /* a failing controller (rev. 2): the fallback on consecutive tasks of the law's modes */
  int law_ran = mode == ECU_ACTIVE || mode == ECU_DEGRADED;
  node->fallback_streak = law_ran && (faults & ECU_SOLVER_FALLBACK) ? node->fallback_streak + 1 : 0;
  ecu_tx_command(&node->tx, mode, mode == ECU_ACTIVE || mode == ECU_DEGRADED || mode == ECU_SAFE_STOP, steer, torque);
  ecu_when_t tx = {node->realtime, node->realtime ? os_monotonic_ns() : 0};
  ecu_tx_diag(&node->tx, r.qp_status, r.solve_time_s, wall_seconds() - started_s, r.iterations, node->overruns, faults);
  record_timing(node, release_jitter_s, wall_seconds() - started_s, r.solve_time_s, now_ns, tx);
}
