/*
 * The node's inputs (firmware_sim/rx.py): RxState, the PlantSampleAssembler (models/plant_sample.py) of the three plant
 * frames and the plausibility checks, on the E2E monitor and codecs of ecu_rx.c.
 */
#ifndef ECU_RX_STATE_H
#define ECU_RX_STATE_H

#include <stdint.h>

#include "ecu_contract.h"
#include "ecu_rx.h"

/* PlantMeasurement: one plant sample as assembled, with its counter. */
typedef struct {
  double vx, vy, yaw_rate, x, y, yaw, steer_angle, drive_torque;
  int counter;
} ecu_measurement_t;

typedef struct {
  int has_sample, has_planner;
  ecu_measurement_t sample;
  ecu_when_t sample_arrival;
  int planner_engage, planner_path_id;
  double planner_speed;
  ecu_when_t planner_arrival;
  int sample_seen, planner_disengaged_seen;
  /* This cycle's flags (the control task clears them). */
  int e2e_error, torn, stale, implausible, reference_restarted;
  ecu_when_t last_time;
  /* PlantSampleAssembler: set_counter -1: none; set_parts: a bit per frame of the set. */
  int set_counter, set_parts, set_completed;
  double part[3][3];
  ecu_e2e_monitor_t e2e;
  /* The plant's sample period for the continuity check, ms (0: SAMPLE_PERIOD_MS; revision 3
   * allows 25). Configuration: the node sets it again after each reset. */
  int sample_period_ms;
} ecu_rx_state_t;

/* RxState.reset: nothing received, every E2E reference forgotten. */
void ecu_rx_state_reset(ecu_rx_state_t *rx);

/* RxState.receive: one frame arrived at `arrival` (unset in lockstep: the next HIL_SYNC
 * stamps it); returns the TICK of a valid HIL_SYNC, else -1. */
int64_t ecu_rx_state_receive(ecu_rx_state_t *rx, uint32_t id, const uint8_t *data, int length, ecu_when_t arrival);

/* Lockstep: the inputs received since the last HIL_SYNC arrived at now_ns. */
void ecu_rx_state_stamp(ecu_rx_state_t *rx, int64_t now_ns);

/* The sample lost its continuity (a jump of virtual time): none held, the set dropped. */
void ecu_rx_state_drop_sample(ecu_rx_state_t *rx);

#endif
