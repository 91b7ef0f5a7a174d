/*
 * controller/dead_reckoning.py: the pose carried forward on the last sample's velocities
 * while the samples are stale (DEGRADED). A pure function.
 */
#ifndef ECU_DEAD_RECKONING_H
#define ECU_DEAD_RECKONING_H

#include "ecu_types.h"

/* predict_pose: x, y, yaw of s moved on constant velocities over elapsed_s in steps of the
 * control period; 0, or -1 (s unchanged) for a non-finite input or a negative time. */
int ecu_dead_reckoning(ecu_sample_t *s, double elapsed_s);

#endif
