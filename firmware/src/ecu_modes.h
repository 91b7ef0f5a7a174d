/*
 * The node's mode logic: the mode transition (firmware_sim/modes.py), the safe stop's
 * command (firmware_sim/safe_stop.py) and the final guard (firmware_sim/guard.py). Pure
 * functions.
 */
#ifndef ECU_MODES_H
#define ECU_MODES_H

#include "ecu_contract.h"

/* ModeEvents of one control task. */
typedef struct {
  int load_failed, sample_seen, sample_fresh, sample_lost, planner_ok, engage, path_known, rearmed, standstill,
      controller_failed;
} ecu_events_t;

/* modes.transition: the mode after `from` (enum ecu_mode) on these events. */
int ecu_mode_transition(int from, const ecu_events_t *events);

/* safe_stop_command: the steer moved towards 0 at the safe stop's rate from the previous
 * valid steer, braking until standstill. */
void ecu_safe_stop_command(double previous_valid_steer, int standstill, double *steer, double *torque);

/* guard.guard_command: 1 when the command is refused (not finite or outside the limits);
 * then *steer holds the previous valid steer (clipped) and *torque 0. */
int ecu_guard_command(double *steer, double *torque, double previous_valid_steer);

#endif
