/*
 * Identification excitation: firmware_sim/excitation.py in C, operation for operation so
 * that the excited commands equal the Python ECU's (Python's float // and % are ported as
 * CPython computes them, ecu_pyfloat.c; the PRBS bits are the same splitmix64 of seed and
 * index). See ecu_excite.h; this file is the run time (the program's offsets, one
 * engagement), ecu_excite_program.c the loading.
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>

#include "ecu_excite.h"
#include "ecu_path_search.h"
#include "ecu_pyfloat.h"

#define PI 3.141592653589793
#define CONTROL_PERIOD_S 0.025

/* ------------------------------------------------------------------ the PRBS */
/* int(q) modulo 2^64 for a finite q >= 0 (Python's int is unbounded; the PRBS keeps the
 * low 64 bits of seed * C + index + 1, so index modulo 2^64 gives the same bits). */
static uint64_t index_bits(double q) {
  static const double TWO_64 = 18446744073709551616.0;
  return (uint64_t)(q < TWO_64 ? q : fmod(q, TWO_64));
}

/* _bit: +1 or -1 for bit `index` of a seeded sequence (splitmix64 of seed and index). */
static double prbs_bit(int64_t seed, uint64_t index) {
  uint64_t value = (uint64_t)seed * 0x9E3779B97F4A7C15ull + index + 1u;
  value = (value ^ (value >> 30)) * 0xBF58476D1CE4E5B9ull;
  value = (value ^ (value >> 27)) * 0x94D049BB133111EBull;
  value ^= value >> 31;
  return (value & 1u) ? 1.0 : -1.0;
}

/* ------------------------------------------------------------------ the pure functions */
static double steer_amplitude(const ecu_excite_t *ex, double vx) {
  if (ex->program.lateral_accel_mps2 == 0.0) return ex->program.steer_amplitude_rad;
  double speed = fmax(fabs(vx), 1.0);
  double scaled = ex->program.lateral_accel_mps2 * ex->program.wheelbase_m / pow(speed, 2.0);
  return ex->program.steer_amplitude_rad < scaled ? ex->program.steer_amplitude_rad : scaled;
}

static double table_value(const ecu_excite_t *ex, const double *values, double t) {
  if (!values || t < ex->table_time[0] || t > ex->table_time[ex->table_rows - 1]) return 0.0;
  for (int k = 1; k < ex->table_rows; k++) {
    if (t <= ex->table_time[k]) {
      double share = (t - ex->table_time[k - 1]) / (ex->table_time[k] - ex->table_time[k - 1]);
      return values[k - 1] + share * (values[k] - values[k - 1]);
    }
  }
  return values[ex->table_rows - 1];
}

/* excitation_offsets: (steering offset, torque offset) time_active_s after entering ACTIVE.
 * -1 where Python's int() of a bit or step index would raise (an infinite quotient). */
static int offsets(const ecu_excite_t *ex, double time_active_s, double vx, double *steer, double *torque) {
  double t = time_active_s - ex->program.delay_s;
  *steer = *torque = 0.0;
  if (!isfinite(t) || t < 0.0) return 0;
  if (ex->program.torque_amplitude_nm > 0.0) {
    double q = py_floordiv(t, ex->program.torque_hold_s);
    if (!isfinite(q)) return -1;
    *torque = ex->program.torque_amplitude_nm * prbs_bit(ex->program.seed + 1, index_bits(q));
  }
  if (ex->program.kind == ECU_EXCITE_TABLE) {
    *steer = table_value(ex, ex->table_steer, t);
    *torque = table_value(ex, ex->table_has_torque ? ex->table_torque : NULL, t) + *torque;
    return 0;
  }
  double amplitude = steer_amplitude(ex, vx);
  if (ex->program.kind == ECU_EXCITE_CHIRP) {
    double tau = py_mod(t, ex->program.chirp_period_s);
    double rate = (ex->program.chirp_end_hz - ex->program.chirp_start_hz) / ex->program.chirp_period_s;
    double phase = 2.0 * PI * (ex->program.chirp_start_hz * tau + 0.5 * rate * tau * tau);
    *steer = amplitude * sin(phase);
  } else {
    double q = py_floordiv(t, ex->program.hold_s);
    if (!isfinite(q)) return -1;
    if (ex->program.kind == ECU_EXCITE_PRBS) {
      *steer = amplitude * prbs_bit(ex->program.seed, index_bits(q));
    } else {
      static const double STEPS[4] = {1.0, 0.0, -1.0, 0.0}; /* +, 0, -, 0 */
      *steer = amplitude * STEPS[index_bits(q) % 4u];
    }
  }
  return 0;
}

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* ------------------------------------------------------------------ one engagement */
int ecu_excite_enabled(const ecu_excite_t *ex) { return ex->enabled; }

const char *ecu_excite_describe(const ecu_excite_t *ex) { return ex->description; }

void ecu_excite_reset(ecu_excite_t *ex, int new_path_id) {
  ex->started = ex->stopped = ex->has_progress = 0;
  ex->steer_offset = 0.0;
  ex->stopped_reason[0] = '\0';
  ex->path_id = new_path_id;
}

void ecu_excite_step(ecu_excite_t *ex, const ecu_path_pool_t *paths, double now_s, int active, double vx, double x,
                     double y, double *steer, double *torque, double steer_min, double steer_max, double torque_min,
                     double torque_max) {
  if (!ex->enabled) return;
  if (!active) {
    ex->steer_offset = 0.0;
    return;
  }
  double lateral_error = NAN;
  ecu_path_view_t path; /* e_Y: a tracker of its own on the engagement's path, apart from the core's */
  int known = ecu_paths_find(paths, ex->path_id, &path) == 0;
  if (known) lateral_error = ecu_path_track(path.x, path.y, path.s, path.n, x, y, &ex->progress, &ex->has_progress);
  if (!ex->started) {
    ex->started = 1;
    ex->started_s = now_s;
  }
  double bound = ex->program.lateral_error_bound_m;
  if (!ex->stopped && known && !(fabs(lateral_error) <= bound)) {
    char value[40], limit[40];
    snprintf(value, sizeof value, "%.2f", fabs(lateral_error));
    py_repr(limit, sizeof limit, bound);
    snprintf(ex->stopped_reason, sizeof ex->stopped_reason, "|e_Y| = %s m > %s m", value, limit);
    ex->stopped = 1;
    fprintf(stderr, "warning: excitation stopped for this engagement: %s\n", ex->stopped_reason);
  }
  double target_steer = 0.0, torque_offset = 0.0;
  int failed = !ex->stopped && isfinite(vx) ? offsets(ex, now_s - ex->started_s, vx, &target_steer, &torque_offset) : 0;
  if (failed == 0 && !(isfinite(target_steer) && isfinite(torque_offset))) failed = -2;
  if (failed != 0) {
    /* as the Python ECU when the program raises or its target is not finite: ex->stopped, the
     * law's command this cycle */
    if (failed == -1) {
      snprintf(ex->stopped_reason, sizeof ex->stopped_reason, "excitation failed: a step index beyond any integer");
    } else {
      char a[40], b[40];
      py_repr(a, sizeof a, target_steer);
      py_repr(b, sizeof b, torque_offset);
      snprintf(ex->stopped_reason, sizeof ex->stopped_reason, "excitation failed: target not finite (steer %s, torque %s)",
               a, b);
    }
    ex->stopped = 1;
    fprintf(stderr, "error: excitation stopped for this engagement: %s\n", ex->stopped_reason);
    return;
  }
  double max_step = ex->program.steer_rate_limit_rad_s * CONTROL_PERIOD_S;
  ex->steer_offset = ex->steer_offset + fmin(fmax(target_steer - ex->steer_offset, -max_step), max_step);
  double s = *steer + ex->steer_offset, q = *torque + torque_offset;
  *steer = isfinite(s) ? clip(s, steer_min, steer_max) : s;
  *torque = isfinite(q) ? clip(q, torque_min, torque_max) : q;
}
