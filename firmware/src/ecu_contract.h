/*
 * The contract's constants the node uses (firmware_sim/config.py): periods, timeouts,
 * command limits, plausibility bounds. Times in ms unless named otherwise.
 */
#ifndef ECU_CONTRACT_H
#define ECU_CONTRACT_H

#include <stdint.h>

#define NS_PER_MS 1000000LL
#define CONTROL_PERIOD_MS 25
#define SAMPLE_STALE_MS 20
#define SAMPLE_LOST_MS 100
#define PLANNER_TIMEOUT_MS 100
/* A failing controller (rev. 2): its step fell back (FAULTS bit 2) on this many control
 * tasks in a row -> SAFE_STOP; 4 tasks = the 100 ms of SAMPLE_LOST_MS at the period. */
#define CONTROLLER_FAILED_CYCLES 4
#define STEER_LIMIT 0.3        /* rad, also inside the DBC's range */
#define TORQUE_LIMIT 3000.0    /* N m */
#define SAFE_STOP_BRAKE 1500.0 /* N m */
#define SAFE_STOP_STEER_RATE 0.2 /* rad/s */
#define STANDSTILL_SPEED 0.1   /* m/s */
#define MAX_CATCH_UP_TASKS 40
/* Revision 3, the control task released by the plant's samples (--release sample): the
 * window of a control instant N is [N - SAMPLE_WINDOW_EARLY_NS, N + SAMPLE_WATCHDOG_NS),
 * the watchdog releases at its end, two releases are at least MIN_RELEASE_SPACING_NS apart. */
#define SAMPLE_WINDOW_EARLY_NS 2500000LL
#define SAMPLE_WATCHDOG_NS 7500000LL
#define MIN_RELEASE_SPACING_NS 15000000LL
/* Rule 4: a sample set that releases the task moves a 10 ms plant's pending instant by its
 * phase error divided by this (truncated toward zero), so the grid follows the samples. */
#define PHASE_FOLLOW_DIVISOR 8
#define JUMP_THRESHOLD_MS 100
#define BEFORE_TICK_0_MS (-5)
#define HANDSHAKE_TICK 0xFFFFFFFFu
#define TICK_STEP_MS 5
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

/* CTRL_MODE values. */
enum ecu_mode { ECU_INIT = 0, ECU_STANDBY = 1, ECU_ACTIVE = 2, ECU_DEGRADED = 3, ECU_SAFE_STOP = 4, ECU_FAULT = 5 };
/* CTRL_DIAG.FAULTS bits. */
enum ecu_fault_bit { ECU_INPUT_TIMEOUT = 1, ECU_E2E_ERROR = 2, ECU_SOLVER_FALLBACK = 4, ECU_MODEL_RESET = 8 };

/* An optional integer ns time (Python's None). */
typedef struct {
  int set;
  int64_t ns;
} ecu_when_t;

#endif
