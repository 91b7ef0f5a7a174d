/*
 * The ECU node in lockstep (see ecu_node.h). Names follow the Python modules; every
 * threshold is the contract's (firmware_sim/config.py). Times are integer ns; in lockstep
 * an input's arrival is unknown until the HIL_SYNC that follows it stamps it.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "ecu_node.h"
#include "ecu_excite.h"
#include "ecu_core.h"
#include "ecu_npz.h"
#include "ecu_rx.h"
#include "os.h"
#include "vehicle.h"

#define NS_PER_MS 1000000LL
#define CONTROL_PERIOD_MS 25
#define SAMPLE_STALE_MS 20
#define SAMPLE_LOST_MS 100
#define PLANNER_TIMEOUT_MS 100
#define STEER_LIMIT 0.3        /* rad, also inside the DBC's range */
#define TORQUE_LIMIT 3000.0    /* N m */
#define SAFE_STOP_BRAKE 1500.0 /* N m */
#define SAFE_STOP_STEER_RATE 0.2 /* rad/s */
#define STANDSTILL_SPEED 0.1   /* m/s */
#define MAX_CATCH_UP_TASKS 40
#define JUMP_THRESHOLD_MS 100
#define BEFORE_TICK_0_MS (-5)
#define HANDSHAKE_TICK 0xFFFFFFFFu
#define TICK_STEP_MS 5
#define DEAD_RECKONING_TS 0.025
#define PI 3.141592653589793
#define TWO_PI 6.283185307179586
/* Plausibility (contract rev. 2). */
#define VX_MIN (-5.0)
#define VX_MAX 70.0
#define VY_MAX 10.0
#define YAW_RATE_MAX 2.5
#define YAW_MAX (PI + 0.0001)
#define SPEED_MARGIN 5.0
#define POSITION_SLACK 0.2
#define SAMPLE_PERIOD_MS 10
#define CONTINUITY_WINDOW_MS 100

enum mode { INIT = 0, STANDBY = 1, ACTIVE = 2, DEGRADED = 3, SAFE_STOP = 4, FAULT = 5 };
enum fault_bit { INPUT_TIMEOUT = 1, E2E_ERROR = 2, SOLVER_FALLBACK = 4, MODEL_RESET = 8 };

typedef struct {
  double vx, vy, yaw_rate, x, y, yaw, steer_angle, drive_torque;
  int counter;
} measurement_t;

/* An optional integer ns time (Python's None). */
typedef struct {
  int set;
  int64_t ns;
} when_t;

static ecu_send_fn send_frame;
static const char *load_error;

/* RxState */
static struct {
  int has_sample, has_planner;
  measurement_t sample;
  when_t sample_arrival;
  int planner_engage, planner_path_id;
  double planner_speed;
  when_t planner_arrival;
  int sample_seen, planner_disengaged_seen;
  int e2e_error, torn, stale, implausible, reference_restarted;
  when_t last_time;
  /* SampleAssembler */
  int set_counter, set_parts, set_completed; /* set_counter -1: none; set_parts: bit per frame */
  double part[3][3];
} rx;

/* Ecu */
static int mode, awaiting_disengage, active_path_id, pending_model_reset, overruns, cycles;
static double previous_valid_steer;
static int tx_counter[2]; /* STEER_TORQUE_CMD, CTRL_DIAG */
static int synchronised;
static when_t last_tick;
static int64_t timing_count; /* control tasks recorded since the run started */
static int realtime, warned_sync, release_started;
static int64_t next_release;

int ecu_node_mode(void) { return mode; }
int ecu_node_cycles(void) { return cycles; }

static double clamp(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

static void rx_reset(void) {
  memset(&rx, 0, sizeof rx);
  rx.set_counter = -1;
  ecu_e2e_reset();
}

static void reset_run(void) {
  rx_reset();
  tx_counter[0] = tx_counter[1] = 0;
  mode = load_error ? FAULT : INIT;
  awaiting_disengage = 0;
  previous_valid_steer = 0.0;
  active_path_id = -1;
  pending_model_reset = 0;
  overruns = 0;
  cycles = 0;
}

void ecu_node_init(ecu_send_fn send, const char *error) {
  send_frame = send;
  load_error = error;
  synchronised = 0;
  timing_count = 0; /* a new node, a new record (the handshake keeps it, as in Python) */
  realtime = warned_sync = release_started = 0;
  last_tick.set = 0;
  reset_run();
}

/* ------------------------------------------------------------------ TX */
static void send_e2e(uint32_t id, int slot, uint8_t data[8]) {
  data[1] = (uint8_t)((data[1] & 0xF0u) | (unsigned)tx_counter[slot]);
  tx_counter[slot] = (tx_counter[slot] + 1) % 16;
  data[0] = ecu_e2e_crc(id, data);
  send_frame(id, data, 8);
}

/* Physical -> raw as cantools' Python encoder: (value - offset) / scale, rounded half to even. */
static long raw_of(double value, double scale, double lo, double hi) {
  return (long)nearbyint(clamp(value, lo, hi) / scale);
}

static void send_command(int cmd_valid, double steer, double torque) {
  struct vehicle_steer_torque_cmd_t m;
  uint8_t data[8];
  memset(&m, 0, sizeof m);
  m.ctrl_mode = (uint8_t)mode;
  m.cmd_valid = (uint8_t)cmd_valid;
  m.steer_angle_cmd = (int16_t)raw_of(steer, 0.0001, -3.2768, 3.2767);
  m.drive_torque_cmd = (int16_t)raw_of(torque, 0.1, -3276.8, 3276.7);
  vehicle_steer_torque_cmd_pack(data, &m, sizeof data);
  send_e2e(VEHICLE_STEER_TORQUE_CMD_FRAME_ID, 0, data);
}

/* tx.saturate_int: round and clamp to 0..upper (non-finite -> upper). */
static unsigned saturate(double value, unsigned upper) {
  if (!(value == value) || value == INFINITY) return upper;
  double r = nearbyint(value);
  return r < 0.0 ? 0u : (r > (double)upper ? upper : (unsigned)r);
}

static void send_diag(int qp_status, double solve_time_s, double cycle_time_s, int iterations, int faults) {
  struct vehicle_ctrl_diag_t m;
  uint8_t data[8];
  memset(&m, 0, sizeof m);
  m.qp_status = (uint8_t)qp_status;
  m.solve_time_us = (uint16_t)saturate(solve_time_s * 1e6, 0xFFFF);
  m.cycle_time_us = (uint16_t)saturate(cycle_time_s * 1e6, 0xFFFF);
  m.qp_iter = (uint8_t)saturate(iterations, 0xFF);
  m.overruns = (uint8_t)saturate(overruns < 15 ? overruns : 15, 15);
  m.faults = (uint8_t)(faults & 0xF);
  vehicle_ctrl_diag_pack(data, &m, sizeof data);
  send_e2e(VEHICLE_CTRL_DIAG_FRAME_ID, 1, data);
}

static void send_ack(uint32_t tick) {
  struct vehicle_hil_sync_ack_t m = {tick};
  uint8_t data[8];
  vehicle_hil_sync_ack_pack(data, &m, sizeof data);
  send_frame(VEHICLE_HIL_SYNC_ACK_FRAME_ID, data, 8);
}

/* ------------------------------------------------------------------ RX */
static int64_t last_good_age(when_t arrival, int *known) {
  *known = rx.has_sample;
  if (!rx.has_sample) return 0;
  when_t now = arrival.set ? arrival : rx.last_time;
  if (!rx.sample_arrival.set || !now.set) return 0; /* the last good sample arrived in this tick */
  int64_t age = now.ns - rx.sample_arrival.ns;
  return age > 0 ? age : 0;
}

/* rx.implausibility: 1 when the sample fails the range or continuity checks. */
static int implausible(const measurement_t *s, when_t arrival) {
  if (!(VX_MIN <= s->vx && s->vx <= VX_MAX) || fabs(s->vy) > VY_MAX || fabs(s->yaw_rate) > YAW_RATE_MAX ||
      fabs(s->yaw) > YAW_MAX)
    return 1;
  int known;
  int64_t age = last_good_age(arrival, &known);
  if (!known || age > CONTINUITY_WINDOW_MS * NS_PER_MS) return 0;
  const measurement_t *last = &rx.sample;
  double elapsed = SAMPLE_PERIOD_MS / 1000.0 * (double)(((s->counter - last->counter) % 16 + 16) % 16);
  double speed = fmax(hypot(s->vx, s->vy), hypot(last->vx, last->vy));
  double allowed = (speed + SPEED_MARGIN) * elapsed + POSITION_SLACK;
  return hypot(s->x - last->x, s->y - last->y) > allowed;
}

/* SampleAssembler.add and what RxState does with a completed sample. */
static void add_plant_frame(int part, const double *values, int counter, when_t arrival) {
  if (counter != rx.set_counter) {
    if (rx.set_parts && !rx.set_completed) rx.torn = 1;
    rx.set_counter = counter;
    rx.set_parts = 0;
    rx.set_completed = 0;
  }
  if (rx.set_completed) return; /* a late duplicate of a set already used */
  memcpy(rx.part[part], values, 3 * sizeof(double));
  rx.set_parts |= 1 << part;
  if (rx.set_parts != 7) return;
  rx.set_completed = 1;
  measurement_t s = {rx.part[0][0], rx.part[0][1], rx.part[0][2], rx.part[1][0], rx.part[1][1],
                     rx.part[2][0], rx.part[2][1], rx.part[2][2], counter};
  if (arrival.set) rx.last_time = arrival;
  if (implausible(&s, arrival)) {
    rx.implausible = 1;
    fprintf(stderr, "warning: plant sample CNT %d not plausible; not used\n", counter);
    return;
  }
  int known;
  int64_t age = last_good_age(arrival, &known);
  if (rx.has_sample && !(known && age <= CONTINUITY_WINDOW_MS * NS_PER_MS)) rx.reference_restarted = 1;
  rx.sample = s;
  rx.has_sample = 1;
  rx.sample_arrival = arrival;
  rx.sample_seen = 1;
}

/* RxState.receive; returns the TICK of a valid HIL_SYNC, else -1. */
static int64_t rx_receive(uint32_t id, const uint8_t *data, int length, when_t arrival) {
  double values[3];
  int part;
  switch (id) {
    case VEHICLE_HIL_SYNC_FRAME_ID: part = -2; break;
    case VEHICLE_PLANNER_REQ_FRAME_ID: part = -1; break;
    case VEHICLE_VEH_DYN_FRAME_ID: part = 0; break;
    case VEHICLE_VEH_POSE_XY_FRAME_ID: part = 1; break;
    case VEHICLE_VEH_POSE_YAW_FRAME_ID: part = 2; break;
    default: return -1; /* somebody else's traffic */
  }
  ecu_e2e_result_t result = ecu_e2e_check(id, data, length);
  if (part == -2) {
    if (result.status == ECU_E2E_WRONG_LENGTH || result.status == ECU_E2E_BAD_TICK) {
      rx.e2e_error = 1;
      return -1;
    }
  } else {
    int e2e_error = result.status == ECU_E2E_CRC_ERROR || result.status == ECU_E2E_REPEATED ||
                    result.status == ECU_E2E_SEQUENCE_ERROR || result.status == ECU_E2E_WRONG_LENGTH ||
                    result.status == ECU_E2E_BAD_TICK;
    if (e2e_error) {
      rx.e2e_error = 1;
      if (result.status == ECU_E2E_REPEATED && part >= 0) rx.stale = 1;
    }
    if (!result.accepted) return -1;
  }
  if (length != 8) {
    rx.e2e_error = 1;
    return -1;
  }
  ecu_decode(id, data, values);
  if (part == -2) {
    uint32_t tick = (uint32_t)values[0];
    if (tick != HANDSHAKE_TICK && tick % TICK_STEP_MS) {
      rx.e2e_error = 1;
      return -1;
    }
    return (int64_t)tick;
  }
  if (part == -1) {
    rx.has_planner = 1;
    rx.planner_engage = values[0] != 0.0;
    rx.planner_speed = values[1];
    rx.planner_path_id = (int)values[2];
    rx.planner_arrival = arrival;
    if (!rx.planner_engage) rx.planner_disengaged_seen = 1;
    return -1;
  }
  add_plant_frame(part, values, data[1] & 0x0F, arrival);
  return -1;
}

static void stamp_pending(int64_t now_ns) {
  rx.last_time.set = 1;
  rx.last_time.ns = now_ns;
  if (rx.has_sample && !rx.sample_arrival.set) rx.sample_arrival = rx.last_time;
  if (rx.has_planner && !rx.planner_arrival.set) rx.planner_arrival = rx.last_time;
}

/* ------------------------------------------------------------------ control task */
typedef struct {
  int load_failed, sample_seen, sample_fresh, sample_lost, planner_ok, engage, path_known, rearmed, standstill;
} events_t;

/* modes.transition */
static int transition(int from, const events_t *e) {
  if (from == FAULT) return FAULT;
  if (e->load_failed) return FAULT;
  if (from == INIT) return e->sample_seen ? STANDBY : INIT;
  int disengage = !e->planner_ok || !e->engage || !e->path_known;
  if (from == STANDBY) return !disengage && e->rearmed && e->sample_fresh ? ACTIVE : STANDBY;
  if (from == SAFE_STOP) return disengage && e->standstill ? STANDBY : SAFE_STOP;
  if (e->sample_lost) return SAFE_STOP;
  if (disengage) return STANDBY;
  if (!e->sample_fresh) return DEGRADED;
  return ACTIVE;
}

/* controller/dead_reckoning.predict_pose: constant velocities over elapsed_s, steps of Ts. */
static int dead_reckoning(ecu_sample_t *s, double elapsed_s) {
  if (!(isfinite(s->x) && isfinite(s->y) && isfinite(s->yaw) && isfinite(s->vx) && isfinite(s->vy) &&
        isfinite(s->yaw_rate) && isfinite(elapsed_s) && elapsed_s >= 0.0))
    return -1;
  double x = s->x, y = s->y, yaw = s->yaw;
  int n_steps = elapsed_s > 0.0 ? (int)ceil(elapsed_s / DEAD_RECKONING_TS - 1e-9) : 0;
  for (int step = 0; step < n_steps; step++) {
    double dt = fmin(DEAD_RECKONING_TS, elapsed_s - step * DEAD_RECKONING_TS);
    double nx = x + dt * (s->vx * cos(yaw) - s->vy * sin(yaw));
    double ny = y + dt * (s->vx * sin(yaw) + s->vy * cos(yaw));
    yaw = yaw + dt * s->yaw_rate;
    x = nx;
    y = ny;
  }
  if (!(yaw >= -PI && yaw < PI)) {
    double m = fmod(yaw + PI, TWO_PI);
    if (m < 0.0) m += TWO_PI;
    yaw = m - PI;
  }
  s->x = x;
  s->y = y;
  s->yaw = yaw;
  return 0;
}

typedef struct {
  double steer, torque, solve_time_s;
  int qp_status, iterations, faults;
} request_t;

static request_t make_request(int previous_mode, const events_t *e, int64_t sample_age, int64_t now_ns) {
  request_t r = {previous_valid_steer, 0.0, 0.0, ECU_NOT_RUN, 0, 0};
  char err[256];
  if (mode == SAFE_STOP) {
    double max_step = SAFE_STOP_STEER_RATE * (CONTROL_PERIOD_MS / 1000.0);
    r.steer = previous_valid_steer - clamp(previous_valid_steer, -max_step, max_step);
    r.torque = e->standstill ? 0.0 : -fabs(SAFE_STOP_BRAKE);
    return r;
  }
  if (mode != ACTIVE && mode != DEGRADED) return r; /* CMD_VALID = 0: hold, no torque */
  if ((previous_mode != ACTIVE && previous_mode != DEGRADED) || active_path_id != rx.planner_path_id) {
    r.faults |= MODEL_RESET;
    ecu_reset();
    if (ecu_path_pool_select(rx.planner_path_id, err, sizeof err) != 0) {
      active_path_id = -1;
      fprintf(stderr, "error: set_path(PATH_ID %d) failed: %s\n", rx.planner_path_id, err);
      r.steer = r.torque = NAN;
      return r;
    }
    active_path_id = rx.planner_path_id;
    ecu_excite_reset(active_path_id); /* a new engagement: the program starts again */
  }
  const measurement_t *m = &rx.sample;
  ecu_sample_t sample = {m->vx, m->vy, m->yaw_rate, m->x, m->y, m->yaw, m->steer_angle, m->drive_torque,
                         rx.planner_speed};
  if (mode == DEGRADED && dead_reckoning(&sample, (double)sample_age / 1e9) != 0) {
    r.steer = r.torque = NAN;
    return r;
  }
  static ecu_output_t out;
  ecu_step(&sample, &out);
  if (out.fallback) r.faults |= SOLVER_FALLBACK;
  if (out.observer_reset) r.faults |= MODEL_RESET;
  r.steer = out.steer_angle;
  r.torque = out.drive_torque;
  /* --excite: the identification excitation on the law's command (ACTIVE only) */
  ecu_excite_step((double)now_ns / 1e9, mode == ACTIVE, m->vx, m->x, m->y, &r.steer, &r.torque, -STEER_LIMIT,
                  STEER_LIMIT, -TORQUE_LIMIT, TORQUE_LIMIT);
  r.qp_status = out.status;
  r.iterations = out.iterations;
  r.solve_time_s = out.solve_time_s;
  return r;
}

static double wall_seconds(void);

/* The timing record (firmware_sim.timing.TimingRecorder): the last TIMING_CAPACITY control
 * tasks, fields TIMING_FIELDS (s; overruns a count) and the context start_time, mode. */
#define TIMING_CAPACITY 65536
#define N_TIMING_FIELDS 6
static double timing_rows[TIMING_CAPACITY][N_TIMING_FIELDS];
static double timing_context[TIMING_CAPACITY][2];

static void record_timing(double release_jitter_s, double task_time_s, double solve_time_s, int64_t now_ns,
                          when_t tx) {
  double input_age = NAN, latency = NAN;
  if (realtime && rx.has_sample && rx.sample_arrival.set && tx.set) {
    input_age = (double)(now_ns - rx.sample_arrival.ns) / 1e9;
    latency = (double)(tx.ns - rx.sample_arrival.ns) / 1e9;
  }
  int64_t i = timing_count % TIMING_CAPACITY;
  const double row[N_TIMING_FIELDS] = {release_jitter_s, task_time_s, solve_time_s, input_age, latency,
                                       (double)overruns};
  memcpy(timing_rows[i], row, sizeof row);
  timing_context[i][0] = (double)now_ns / 1e9;
  timing_context[i][1] = mode;
  timing_count++;
}

static void control_task(int64_t now_ns, double release_jitter_s, double started_s) {
  events_t e;
  cycles++;
  int has_age = rx.has_sample && rx.sample_arrival.set;
  int64_t age = has_age ? now_ns - rx.sample_arrival.ns : 0;
  e.load_failed = load_error != NULL;
  e.sample_seen = rx.sample_seen;
  e.sample_fresh = has_age && age <= SAMPLE_STALE_MS * NS_PER_MS;
  e.sample_lost = !has_age || age > SAMPLE_LOST_MS * NS_PER_MS || rx.reference_restarted;
  e.planner_ok = rx.has_planner && rx.planner_arrival.set &&
                 now_ns - rx.planner_arrival.ns <= PLANNER_TIMEOUT_MS * NS_PER_MS;
  if (awaiting_disengage && rx.planner_disengaged_seen) awaiting_disengage = 0;
  e.standstill = e.sample_fresh && rx.has_sample && fabs(rx.sample.vx) < STANDSTILL_SPEED;
  e.engage = rx.has_planner && rx.planner_engage;
  e.path_known = rx.has_planner && ecu_path_pool_has(rx.planner_path_id);
  e.rearmed = !awaiting_disengage;
  int previous_mode = mode;
  mode = transition(previous_mode, &e);
  if (mode != previous_mode && mode == SAFE_STOP) {
    awaiting_disengage = 1;
    rx.planner_disengaged_seen = 0;
  }
  /* FAULTS bits 0 and 1 of this cycle, then the next cycle's RX flags start. */
  int faults = 0, unknown_path = rx.has_planner && !e.path_known;
  if (!e.sample_fresh || rx.torn || rx.stale || rx.implausible || !e.planner_ok || unknown_path)
    faults |= INPUT_TIMEOUT;
  if (rx.e2e_error) faults |= E2E_ERROR;
  rx.e2e_error = rx.torn = rx.stale = rx.implausible = rx.reference_restarted = 0;
  if (pending_model_reset) {
    faults |= MODEL_RESET;
    pending_model_reset = 0;
  }
  request_t r = make_request(previous_mode, &e, age, now_ns);
  faults |= r.faults;
  /* guard.guard_command */
  double steer = r.steer, torque = r.torque;
  if (!isfinite(steer) || !isfinite(torque) || steer < -STEER_LIMIT || steer > STEER_LIMIT ||
      torque < -TORQUE_LIMIT || torque > TORQUE_LIMIT) {
    faults |= SOLVER_FALLBACK;
    steer = clamp(isfinite(previous_valid_steer) ? previous_valid_steer : 0.0, -STEER_LIMIT, STEER_LIMIT);
    torque = 0.0;
  }
  previous_valid_steer = steer;
  send_command(mode == ACTIVE || mode == DEGRADED || mode == SAFE_STOP, steer, torque);
  when_t tx = {realtime, realtime ? os_monotonic_ns() : 0};
  send_diag(r.qp_status, r.solve_time_s, wall_seconds() - started_s, r.iterations, faults);
  record_timing(release_jitter_s, wall_seconds() - started_s, r.solve_time_s, now_ns, tx);
}

/* ------------------------------------------------------------------ lockstep */

static double wall_seconds(void) { return 1e-9 * (double)os_monotonic_ns(); }

static void on_tick(uint32_t tick) {
  double started = wall_seconds();
  if (tick == HANDSHAKE_TICK) {
    synchronised = 1;
    last_tick.set = 0;
    reset_run();
    send_ack(HANDSHAKE_TICK);
    return;
  }
  if (!synchronised) return;
  int64_t t = (int64_t)tick;
  if (last_tick.set && t == last_tick.ns) { /* repeated: acknowledged again, nothing run */
    stamp_pending(t * NS_PER_MS);
    send_ack(tick);
    return;
  }
  if (last_tick.set && t < last_tick.ns) {
    rx.e2e_error = 1;
    fprintf(stderr, "warning: HIL_SYNC TICK %u older than the last TICK: discarded\n", tick);
    return;
  }
  int64_t after = last_tick.set ? last_tick.ns : BEFORE_TICK_0_MS;
  int64_t first = ((after >= 0 ? after / CONTROL_PERIOD_MS : -((-after + CONTROL_PERIOD_MS - 1) / CONTROL_PERIOD_MS)) + 1) *
                  CONTROL_PERIOD_MS;
  int64_t due_first, due_count;
  if (t - after > JUMP_THRESHOLD_MS) {
    /* A jump of virtual time (rev. 2): adopted, STANDBY, memories cleared; only a task due
     * at the TICK itself runs. */
    fprintf(stderr, "warning: HIL_SYNC TICK %u: virtual time jumped; controller reset\n", tick);
    if (mode != FAULT && mode != INIT) mode = STANDBY;
    rx.has_sample = 0;
    rx.sample_arrival.set = 0;
    rx.set_counter = -1;
    rx.set_parts = rx.set_completed = 0;
    rx.e2e_error = 1;
    pending_model_reset = 1;
    active_path_id = -1;
    ecu_reset();
    due_first = t;
    due_count = t % CONTROL_PERIOD_MS == 0;
  } else {
    int64_t count = first > t ? 0 : (t - first) / CONTROL_PERIOD_MS + 1;
    int64_t skipped = count > MAX_CATCH_UP_TASKS ? count - MAX_CATCH_UP_TASKS : 0;
    due_first = first + skipped * CONTROL_PERIOD_MS;
    due_count = count - skipped;
  }
  (void)due_first;
  last_tick.set = 1;
  last_tick.ns = t;
  stamp_pending(t * NS_PER_MS);
  for (int64_t k = 0; k < due_count; k++) control_task(t * NS_PER_MS, NAN, wall_seconds());
  send_ack(tick);
  if (wall_seconds() - started > CONTROL_PERIOD_MS / 1000.0) overruns++;
}

void ecu_node_receive(uint32_t id, const uint8_t *data, int length, int contract_kind) {
  /* lockstep: the arrival is stamped by the next HIL_SYNC; real time: now */
  when_t arrival = {realtime, realtime ? os_monotonic_ns() : 0};
  if (!contract_kind) return; /* rev. 2: never taken for a contract frame, never FAULTS */
  int64_t tick = rx_receive(id, data, length, arrival);
  if (tick < 0) return;
  if (!realtime) on_tick((uint32_t)tick);
  else if (!warned_sync) {
    warned_sync = 1;
    fprintf(stderr, "warning: HIL_SYNC ignored in real-time mode\n");
  }
}

/* ------------------------------------------------------------------ real time */
void ecu_node_set_realtime(void) { realtime = 1; }

int64_t ecu_node_poll(int64_t now_ns) {
  const int64_t period = CONTROL_PERIOD_MS * NS_PER_MS;
  if (!realtime) return 0;
  if (!release_started) {
    next_release = now_ns;
    release_started = 1;
  }
  if (now_ns < next_release) return next_release;
  /* RealtimeSchedule.release: absolute releases (next += period); whole periods missed
   * are skipped, not run in a burst, and counted as overruns. */
  int64_t ideal = next_release;
  next_release = ideal + period;
  if (now_ns >= next_release) {
    int64_t skipped = (now_ns - next_release) / period + 1;
    next_release += skipped * period;
    overruns += (int)skipped;
  }
  control_task(now_ns, (double)(now_ns - ideal) / 1e9, 1e-9 * (double)now_ns);
  if (os_monotonic_ns() > ideal + period) overruns++;
  return next_release;
}

void ecu_node_close(void) {
  int final_mode = mode == FAULT ? FAULT : STANDBY;
  int saved = mode;
  mode = final_mode;
  send_command(0, previous_valid_steer, 0.0);
  mode = saved;
}

/* Reverse the rows lo..hi-1 of a ring (row_len doubles each), in place. */
static void reverse_rows(double *base, int row_len, int64_t lo, int64_t hi) {
  double tmp[N_TIMING_FIELDS];
  for (hi--; lo < hi; lo++, hi--) {
    memcpy(tmp, base + lo * row_len, (size_t)row_len * sizeof(double));
    memcpy(base + lo * row_len, base + hi * row_len, (size_t)row_len * sizeof(double));
    memcpy(base + hi * row_len, tmp, (size_t)row_len * sizeof(double));
  }
}

int ecu_node_save_timing(const char *path, char *err, size_t err_len) {
  static const char fields[N_TIMING_FIELDS][16] = {"release_jitter", "task_time", "solve_time", "input_age",
                                                   "rx_to_tx_latency", "overruns"};
  static const char context_fields[2][10] = {"start_time", "mode"};
  static uint32_t field_text[N_TIMING_FIELDS][16], context_text[2][10]; /* numpy '<U': UTF-32 */
  int64_t n = timing_count < TIMING_CAPACITY ? timing_count : TIMING_CAPACITY;
  int64_t first = timing_count < TIMING_CAPACITY ? 0 : timing_count % TIMING_CAPACITY;
  /* Oldest first, as TimingRecorder.rows(): rotate the full ring in place (three
   * reversals), so no second buffer is needed; the record is written once, at exit. */
  if (first) {
    reverse_rows(&timing_rows[0][0], N_TIMING_FIELDS, 0, first);
    reverse_rows(&timing_rows[0][0], N_TIMING_FIELDS, first, n);
    reverse_rows(&timing_rows[0][0], N_TIMING_FIELDS, 0, n);
    reverse_rows(&timing_context[0][0], 2, 0, first);
    reverse_rows(&timing_context[0][0], 2, first, n);
    reverse_rows(&timing_context[0][0], 2, 0, n);
  }
  for (int f = 0; f < N_TIMING_FIELDS; f++)
    for (int c = 0; c < 16; c++) field_text[f][c] = (uint8_t)fields[f][c];
  for (int f = 0; f < 2; f++)
    for (int c = 0; c < 10; c++) context_text[f][c] = (uint8_t)context_fields[f][c];
  char rows_shape[40], context_shape[40];
  snprintf(rows_shape, sizeof rows_shape, "(%lld, %d)", (long long)n, N_TIMING_FIELDS);
  snprintf(context_shape, sizeof context_shape, "(%lld, 2)", (long long)n);
  int64_t count = timing_count;
  const npz_array_t arrays[] = {
    {"rows", "<f8", rows_shape, timing_rows, (size_t)n * sizeof timing_rows[0]},
    {"context", "<f8", context_shape, timing_context, (size_t)n * sizeof timing_context[0]},
    {"fields", "<U16", "(6,)", field_text, sizeof field_text},
    {"context_fields", "<U10", "(2,)", context_text, sizeof context_text},
    {"count", "<i8", "()", &count, sizeof count},
  };
  return npz_write(path, arrays, 5, err, err_len);
}
