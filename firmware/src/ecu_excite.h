/*
 * Identification excitation (--excite PROGRAM): a port of firmware_sim/excitation.py.
 * A known steering (and drive torque) signal is added to the law's command while ACTIVE,
 * rate limited, clipped to the command limits, and stopped for the rest of the engagement
 * once |e_Y| exceeds the program's bound. Programs: the shipped ones (chirp, prbs, steps,
 * prbs-torque), a .toml file of ExcitationProgram's fields, or a .csv table
 * time_s,steer_rad[,torque_nm] of at most ECU_EXCITE_TABLE_MAX rows. All of it is one
 * ecu_excite_t, the caller's storage (static or zeroed: no heap; zeroed is disabled).
 * Loading (ecu_excite_program.c) is start-up only; the step (ecu_excite.c) never fails.
 */
#ifndef ECU_EXCITE_H
#define ECU_EXCITE_H

#include <stddef.h>
#include <stdint.h>

#include "ecu_path_reader.h"

/* Rows of a table program (a larger file is refused, naming the file and this limit). */
#define ECU_EXCITE_TABLE_MAX 20000

enum ecu_excite_kind { ECU_EXCITE_CHIRP, ECU_EXCITE_PRBS, ECU_EXCITE_STEPS, ECU_EXCITE_TABLE };

/* ExcitationProgram (SI units; times relative to entering ACTIVE). */
typedef struct {
  char name[128];
  int kind;
  double steer_amplitude_rad, lateral_accel_mps2, wheelbase_m;
  double chirp_start_hz, chirp_end_hz, chirp_period_s, hold_s;
  int64_t seed;
  double torque_amplitude_nm, torque_hold_s, delay_s, steer_rate_limit_rad_s, lateral_error_bound_m;
} ecu_excite_program_t;

typedef struct {
  ecu_excite_program_t program;
  int enabled;
  double table_time[ECU_EXCITE_TABLE_MAX], table_steer[ECU_EXCITE_TABLE_MAX], table_torque[ECU_EXCITE_TABLE_MAX];
  int table_rows, table_has_torque;
  char description[700];
  /* One engagement's state (Excitation): start, applied offset, stop; e_Y's tracker. */
  int started, stopped, path_id, has_progress;
  double started_s, steer_offset, progress;
  char stopped_reason[200];
} ecu_excite_t;

/* Start-up: load the program `spec` (a shipped name or a .toml / .csv file) and enable
 * the excitation. 0, or -1 and one line in err naming the file and the field (the
 * messages of firmware_sim/excitation.py). */
int ecu_excite_load(ecu_excite_t *excite, const char *spec, char *err, size_t err_len);

/* Whether `spec` names a program file (not one of the shipped programs). */
int ecu_excite_is_file(const char *spec);

/* Whether a program is loaded; its one-line description (excitation.describe). */
int ecu_excite_enabled(const ecu_excite_t *excite);
const char *ecu_excite_describe(const ecu_excite_t *excite);

/* A new engagement on PATH_ID path_id (entering ACTIVE / DEGRADED or a path change): the
 * program starts again, a stop is forgotten, e_Y is tracked on that path anew. */
void ecu_excite_reset(ecu_excite_t *excite, int path_id);

/* One control task: the law's command (*steer rad, *torque N m) with the excitation
 * superimposed when `active` (mode ACTIVE), else unchanged. now_s: the task's time (virtual
 * time in lockstep), vx the measured speed, x / y the measured position (e_Y on the path
 * of paths the engagement runs on). A non-finite command stays non-finite (the final guard
 * refuses it). */
void ecu_excite_step(ecu_excite_t *excite, const ecu_path_pool_t *paths, double now_s, int active, double vx,
                     double x, double y, double *steer, double *torque, double steer_min, double steer_max,
                     double torque_min, double torque_max);

#endif
