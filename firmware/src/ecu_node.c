/*
 * The ECU node (see ecu_node.h): its start, the lockstep time base (HIL_SYNC ticks,
 * firmware_sim/clock.py LockstepClock) and the real-time releases (RealtimeSchedule).
 * Every threshold is the contract's (ecu_contract.h).
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "ecu_control_task.h"
#include "ecu_node.h"
#include "os.h"

static double wall_seconds(void) { return 1e-9 * (double)os_monotonic_ns(); }

static void reset_run(ecu_node_t *node) {
  ecu_rx_state_reset(&node->rx);
  node->rx.sample_period_ms = node->plant_period_ms;
  node->tx.counter[0] = node->tx.counter[1] = 0;
  node->mode = node->load_error ? ECU_FAULT : ECU_INIT;
  node->awaiting_disengage = 0;
  node->previous_valid_steer = 0.0;
  node->active_path_id = -1;
  node->pending_model_reset = 0;
  node->fallback_streak = 0;
  node->overruns = 0;
  node->cycles = 0;
  ecu_release_reset(&node->release);
  node->release.sample_period_ns = (int64_t)(node->plant_period_ms ? node->plant_period_ms : SAMPLE_PERIOD_MS) * NS_PER_MS;
}

void ecu_node_start(ecu_node_t *node, ecu_core_t *core, const ecu_path_pool_t *paths, ecu_excite_t *excite,
                    ecu_send_fn send, const char *load_error) {
  node->core = core;
  node->paths = paths;
  node->excite = excite;
  node->tx.send = send;
  node->load_error = load_error;
  node->synchronised = 0;
  node->timing.count = 0; /* a new node, a new record (the handshake keeps it, as in Python) */
  node->realtime = node->warned_sync = node->release_started = 0;
  node->sample_release = 0;
  node->plant_period_ms = 0;
  node->last_tick.set = 0;
  reset_run(node);
}


/* One task of revision 3 released at released_ns for the control instant instant_ns. */
static void run_released(ecu_node_t *node, int64_t released_ns, int64_t instant_ns) {
  if (!node->realtime) {
    ecu_control_task(node, released_ns, NAN, wall_seconds());
    return;
  }
  int64_t now = os_monotonic_ns();
  ecu_control_task(node, now, (double)(released_ns - instant_ns) / 1e9, 1e-9 * (double)now);
  if (os_monotonic_ns() > released_ns + CONTROL_PERIOD_MS * NS_PER_MS) node->overruns++;
}

/* The period watchdog of revision 3: an instant whose window closed without a good sample
 * runs now; older unreleased ones are skipped (overruns in real time only: in lockstep
 * OVERRUNS counts wall clock, as in revision 2). */
static void release_by_watchdog(ecu_node_t *node, int64_t now_ns) {
  int skipped;
  int due = ecu_release_on_time(&node->release, now_ns, &skipped);
  if (node->realtime) node->overruns += skipped;
  if (due) run_released(node, now_ns, node->release.instant_ns - CONTROL_PERIOD_MS * NS_PER_MS);
}

/* A good plant sample set arrived (revision 3): windows closed by now first, then the
 * sample's own release. */
static void on_good_sample(ecu_node_t *node, int64_t arrival_ns) {
  if (node->release.anchored) release_by_watchdog(node, arrival_ns);
  if (ecu_release_on_sample(&node->release, arrival_ns)) run_released(node, arrival_ns, node->release.instant_ns);
}

static void on_tick(ecu_node_t *node, uint32_t tick) {
  ecu_rx_state_t *rx = &node->rx;
  double started = wall_seconds();
  if (tick == HANDSHAKE_TICK) {
    node->synchronised = 1;
    node->last_tick.set = 0;
    reset_run(node);
    ecu_tx_ack(&node->tx, HANDSHAKE_TICK);
    return;
  }
  if (!node->synchronised) return;
  int64_t t = (int64_t)tick;
  if (node->last_tick.set && t == node->last_tick.ns) { /* repeated: acknowledged again, nothing run */
    ecu_rx_state_stamp(rx, t * NS_PER_MS);
    ecu_tx_ack(&node->tx, tick);
    return;
  }
  if (node->last_tick.set && t < node->last_tick.ns) {
    rx->e2e_error = 1;
    fprintf(stderr, "warning: HIL_SYNC TICK %u older than the last TICK: discarded\n", tick);
    return;
  }
  int64_t after = node->last_tick.set ? node->last_tick.ns : BEFORE_TICK_0_MS;
  int64_t first = ((after >= 0 ? after / CONTROL_PERIOD_MS : -((-after + CONTROL_PERIOD_MS - 1) / CONTROL_PERIOD_MS)) + 1) *
                  CONTROL_PERIOD_MS;
  int64_t due_first, due_count;
  if (t - after > JUMP_THRESHOLD_MS) {
    /* A jump of virtual time (rev. 2): adopted, STANDBY, memories cleared; only a task due
     * at the TICK itself runs. */
    fprintf(stderr, "warning: HIL_SYNC TICK %u: virtual time jumped; controller reset\n", tick);
    if (node->mode != ECU_FAULT && node->mode != ECU_INIT) node->mode = ECU_STANDBY;
    ecu_rx_state_drop_sample(rx);
    rx->e2e_error = 1;
    node->pending_model_reset = 1;
    node->fallback_streak = 0; /* the core starts afresh: no failing streak spans the jump */
    node->active_path_id = -1;
    ecu_core_reset(node->core);
    ecu_release_reset(&node->release); /* revision 3: the grid anchors again at the next sample */
    due_first = t;
    due_count = t % CONTROL_PERIOD_MS == 0;
  } else {
    int64_t count = first > t ? 0 : (t - first) / CONTROL_PERIOD_MS + 1;
    int64_t skipped = count > MAX_CATCH_UP_TASKS ? count - MAX_CATCH_UP_TASKS : 0;
    due_first = first + skipped * CONTROL_PERIOD_MS;
    due_count = count - skipped;
  }
  (void)due_first;
  node->last_tick.set = 1;
  node->last_tick.ns = t;
  /* a good sample of this tick (its frames came before HIL_SYNC): stamped just below */
  int new_sample = rx->has_sample && !rx->sample_arrival.set;
  ecu_rx_state_stamp(rx, t * NS_PER_MS);
  if (!node->sample_release || !node->release.anchored) {
    /* revision 2's clock (revision 3: until a sample anchors the grid) */
    for (int64_t k = 0; k < due_count; k++) {
      ecu_control_task(node, t * NS_PER_MS, NAN, wall_seconds());
      if (node->sample_release) ecu_release_note(&node->release, t * NS_PER_MS);
    }
  } else {
    release_by_watchdog(node, t * NS_PER_MS);
  }
  if (node->sample_release && new_sample) on_good_sample(node, t * NS_PER_MS);
  ecu_tx_ack(&node->tx, tick);
  if (wall_seconds() - started > CONTROL_PERIOD_MS / 1000.0) node->overruns++;
}

void ecu_node_frame(ecu_node_t *node, uint32_t id, const uint8_t *data, int length, int contract_kind) {
  /* lockstep: the arrival is stamped by the next HIL_SYNC; real time: now */
  ecu_when_t arrival = {node->realtime, node->realtime ? os_monotonic_ns() : 0};
  if (!contract_kind) return; /* rev. 2: never taken for a contract frame, never FAULTS */
  ecu_when_t sample_before = node->rx.has_sample ? node->rx.sample_arrival : (ecu_when_t){0, 0};
  int64_t tick = ecu_rx_state_receive(&node->rx, id, data, length, arrival);
  if (node->sample_release && node->realtime && node->rx.has_sample && node->rx.sample_arrival.set &&
      node->rx.sample_arrival.ns == arrival.ns && !(sample_before.set && sample_before.ns == arrival.ns))
    on_good_sample(node, arrival.ns); /* a good sample completed by this frame (lockstep: at the TICK) */
  if (tick < 0) return;
  if (!node->realtime) on_tick(node, (uint32_t)tick);
  else if (!node->warned_sync) {
    node->warned_sync = 1;
    fprintf(stderr, "warning: HIL_SYNC ignored in real-time mode\n");
  }
}

/* ------------------------------------------------------------------ real time */
void ecu_node_set_realtime(ecu_node_t *node) { node->realtime = 1; }

void ecu_node_set_sample_release(ecu_node_t *node) { node->sample_release = 1; }

void ecu_node_set_plant_period(ecu_node_t *node, int period_ms) {
  node->plant_period_ms = period_ms;
  node->rx.sample_period_ms = period_ms;
  node->release.sample_period_ns = (int64_t)period_ms * NS_PER_MS;
}

int64_t ecu_node_poll(ecu_node_t *node, int64_t now_ns) {
  const int64_t period = CONTROL_PERIOD_MS * NS_PER_MS;
  if (!node->realtime) return 0;
  if (node->sample_release && node->release.anchored) {
    release_by_watchdog(node, now_ns);
    return node->release.instant_ns + SAMPLE_WATCHDOG_NS;
  }
  if (!node->release_started) {
    node->next_release = now_ns;
    node->release_started = 1;
  }
  if (now_ns < node->next_release) return node->next_release;
  /* RealtimeSchedule.release: absolute releases (next += period); whole periods missed
   * are skipped, not run in a burst, and counted as overruns. */
  int64_t ideal = node->next_release;
  node->next_release = ideal + period;
  if (now_ns >= node->next_release) {
    int64_t skipped = (now_ns - node->next_release) / period + 1;
    node->next_release += skipped * period;
    node->overruns += (int)skipped;
  }
  ecu_control_task(node, now_ns, (double)(now_ns - ideal) / 1e9, 1e-9 * (double)now_ns);
  if (node->sample_release) ecu_release_note(&node->release, now_ns);
  if (os_monotonic_ns() > ideal + period) node->overruns++;
  return node->next_release;
}

void ecu_node_close(ecu_node_t *node) {
  int final_mode = node->mode == ECU_FAULT ? ECU_FAULT : ECU_STANDBY;
  ecu_tx_command(&node->tx, final_mode, 0, node->previous_valid_steer, 0.0);
}
