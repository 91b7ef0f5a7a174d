/*
 * Identification excitation (--excite PROGRAM): a port of firmware_sim/excitation.py.
 * A known steering (and drive torque) signal is added to the law's command while ACTIVE,
 * rate limited, clipped to the command limits, and stopped for the rest of the engagement
 * once |e_Y| exceeds the program's bound. Programs: the shipped ones (chirp, prbs, steps,
 * prbs-torque), a .toml file of ExcitationProgram's fields, or a .csv table
 * time_s,steer_rad[,torque_nm] of at most ECU_EXCITE_TABLE_MAX rows (static storage: no
 * heap). Loading is start-up only; the step never fails.
 */
#ifndef ECU_EXCITE_H
#define ECU_EXCITE_H

#include <stddef.h>

#include "ecu_core.h"

/* Rows of a table program (a larger file is refused, naming the file and this limit). */
#define ECU_EXCITE_TABLE_MAX 20000

/* Start-up: load the program `spec` (a shipped name or a .toml / .csv file) and enable
 * the excitation. 0, or -1 and one line in err naming the file and the field (the
 * messages of firmware_sim/excitation.py). */
ECU_API int ecu_excite_load(const char *spec, char *err, size_t err_len);

/* Whether `spec` names a program file (not one of the shipped programs). */
ECU_API int ecu_excite_is_file(const char *spec);

/* Whether a program is loaded; its one-line description (excitation.describe). */
ECU_API int ecu_excite_enabled(void);
ECU_API const char *ecu_excite_describe(void);

/* A new engagement on PATH_ID path_id (entering ACTIVE / DEGRADED or a path change): the
 * program starts again, a stop is forgotten, e_Y is tracked on that path anew. */
ECU_API void ecu_excite_reset(int path_id);

/* One control task: the law's command (*steer rad, *torque N m) with the excitation
 * superimposed when `active` (mode ACTIVE), else unchanged. now_s: the task's time (virtual
 * time in lockstep), vx the measured speed, x / y the measured position (e_Y). A
 * non-finite command stays non-finite (the final guard refuses it). */
ECU_API void ecu_excite_step(double now_s, int active, double vx, double x, double y, double *steer,
                             double *torque, double steer_min, double steer_max, double torque_min,
                             double torque_max);

/* The pool's path PATH_ID: controller.reference.PathTracker.update's signed lateral error
 * (m) at x, y, searched around *progress (the whole path when !*has_progress); updates the
 * progress. 0, or -1 when the path is not loaded (ecu_path.c). */
int ecu_path_pool_track(int path_id, double x, double y, double *progress, int *has_progress,
                        double *lateral_error);

#endif
