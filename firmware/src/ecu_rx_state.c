/*
 * The node's inputs (see ecu_rx_state.h). Times are integer ns; in lockstep an input's
 * arrival is unknown until the HIL_SYNC that follows it stamps it.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "ecu_rx_state.h"
#include "vehicle.h"

void ecu_rx_state_reset(ecu_rx_state_t *rx) {
  memset(rx, 0, sizeof *rx);
  rx->set_counter = -1;
  ecu_e2e_monitor_reset(&rx->e2e);
}

void ecu_rx_state_drop_sample(ecu_rx_state_t *rx) {
  rx->has_sample = 0;
  rx->sample_arrival.set = 0;
  rx->set_counter = -1;
  rx->set_parts = rx->set_completed = 0;
}

static int64_t last_good_age(const ecu_rx_state_t *rx, ecu_when_t arrival, int *known) {
  *known = rx->has_sample;
  if (!rx->has_sample) return 0;
  ecu_when_t now = arrival.set ? arrival : rx->last_time;
  if (!rx->sample_arrival.set || !now.set) return 0; /* the last good sample arrived in this tick */
  int64_t age = now.ns - rx->sample_arrival.ns;
  return age > 0 ? age : 0;
}

/* rx->implausibility: 1 when the sample fails the range or continuity checks. */
static int implausible(const ecu_rx_state_t *rx, const ecu_measurement_t *s, ecu_when_t arrival) {
  if (!(VX_MIN <= s->vx && s->vx <= VX_MAX) || fabs(s->vy) > VY_MAX || fabs(s->yaw_rate) > YAW_RATE_MAX ||
      fabs(s->yaw) > YAW_MAX)
    return 1;
  int known;
  int64_t age = last_good_age(rx, arrival, &known);
  if (!known || age > CONTINUITY_WINDOW_MS * NS_PER_MS) return 0;
  const ecu_measurement_t *last = &rx->sample;
  int period_ms = rx->sample_period_ms ? rx->sample_period_ms : SAMPLE_PERIOD_MS;
  double elapsed = period_ms / 1000.0 * (double)(((s->counter - last->counter) % 16 + 16) % 16);
  double speed = fmax(hypot(s->vx, s->vy), hypot(last->vx, last->vy));
  double allowed = (speed + SPEED_MARGIN) * elapsed + POSITION_SLACK;
  return hypot(s->x - last->x, s->y - last->y) > allowed;
}

/* PlantSampleAssembler.add (models/plant_sample.py) and what RxState does with a completed sample. */
static void add_plant_frame(ecu_rx_state_t *rx, int part, const double *values, int counter, ecu_when_t arrival) {
  if (counter != rx->set_counter) {
    if (rx->set_parts && !rx->set_completed) rx->torn = 1;
    rx->set_counter = counter;
    rx->set_parts = 0;
    rx->set_completed = 0;
  }
  if (rx->set_completed) return; /* a late duplicate of a set already used */
  memcpy(rx->part[part], values, 3 * sizeof(double));
  rx->set_parts |= 1 << part;
  if (rx->set_parts != 7) return;
  rx->set_completed = 1;
  ecu_measurement_t s = {rx->part[0][0], rx->part[0][1], rx->part[0][2], rx->part[1][0], rx->part[1][1],
                     rx->part[2][0], rx->part[2][1], rx->part[2][2], counter};
  if (arrival.set) rx->last_time = arrival;
  if (implausible(rx, &s, arrival)) {
    rx->implausible = 1;
    fprintf(stderr, "warning: plant sample CNT %d not plausible; not used\n", counter);
    return;
  }
  int known;
  int64_t age = last_good_age(rx, arrival, &known);
  if (rx->has_sample && !(known && age <= CONTINUITY_WINDOW_MS * NS_PER_MS)) rx->reference_restarted = 1;
  rx->sample = s;
  rx->has_sample = 1;
  rx->sample_arrival = arrival;
  rx->sample_seen = 1;
}

int64_t ecu_rx_state_receive(ecu_rx_state_t *rx, uint32_t id, const uint8_t *data, int length, ecu_when_t arrival) {
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
  ecu_e2e_result_t result = ecu_e2e_monitor_check(&rx->e2e, id, data, length);
  if (part == -2) {
    if (result.status == ECU_E2E_WRONG_LENGTH || result.status == ECU_E2E_BAD_TICK) {
      rx->e2e_error = 1;
      return -1;
    }
  } else {
    int e2e_error = result.status == ECU_E2E_CRC_ERROR || result.status == ECU_E2E_REPEATED ||
                    result.status == ECU_E2E_SEQUENCE_ERROR || result.status == ECU_E2E_WRONG_LENGTH ||
                    result.status == ECU_E2E_BAD_TICK;
    if (e2e_error) {
      rx->e2e_error = 1;
      if (result.status == ECU_E2E_REPEATED && part >= 0) rx->stale = 1;
    }
    if (!result.accepted) return -1;
  }
  if (length != 8) {
    rx->e2e_error = 1;
    return -1;
  }
  ecu_decode(id, data, values);
  if (part == -2) {
    uint32_t tick = (uint32_t)values[0];
    if (tick != HANDSHAKE_TICK && tick % TICK_STEP_MS) {
      rx->e2e_error = 1;
      return -1;
    }
    return (int64_t)tick;
  }
  if (part == -1) {
    rx->has_planner = 1;
    rx->planner_engage = values[0] != 0.0;
    rx->planner_speed = values[1];
    rx->planner_path_id = (int)values[2];
    rx->planner_arrival = arrival;
    if (!rx->planner_engage) rx->planner_disengaged_seen = 1;
    return -1;
  }
  add_plant_frame(rx, part, values, data[1] & 0x0F, arrival);
  return -1;
}

void ecu_rx_state_stamp(ecu_rx_state_t *rx, int64_t now_ns) {
  rx->last_time.set = 1;
  rx->last_time.ns = now_ns;
  if (rx->has_sample && !rx->sample_arrival.set) rx->sample_arrival = rx->last_time;
  if (rx->has_planner && !rx->planner_arrival.set) rx->planner_arrival = rx->last_time;
}
