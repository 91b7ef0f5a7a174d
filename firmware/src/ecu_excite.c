/*
 * Identification excitation: firmware_sim/excitation.py in C, operation for operation so
 * that the excited commands equal the Python ECU's (Python's float // and % are ported as
 * CPython computes them, the PRBS bits are the same splitmix64 of seed and index). See
 * ecu_excite.h. All storage is static; loading reads the program once at start-up.
 */
#include <ctype.h>
#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ecu_excite.h"
#include "ecu_lines.h"

#define PI 3.141592653589793
#define CONTROL_PERIOD_S 0.025
#define STEER_LIMIT 0.3 /* rad: a program's amplitude may not exceed the command limit */
#define LINE_BYTES (ECU_LINE_MAX + 2)
#define NAME_BYTES 128
#define TABLE_TIME_LIMIT_S 86400.0  /* |time_s| of a table row (excitation.py TABLE_TIME_LIMIT_S) */
#define TABLE_TORQUE_LIMIT_NM 3000.0 /* |torque_nm| of a table row */

enum kind { CHIRP, PRBS, STEPS, TABLE };
static const char *const KIND_NAMES[] = {"chirp", "prbs", "steps", "table"};

/* ExcitationProgram (SI units; times relative to entering ACTIVE). */
typedef struct {
  char name[NAME_BYTES];
  int kind;
  double steer_amplitude_rad, lateral_accel_mps2, wheelbase_m;
  double chirp_start_hz, chirp_end_hz, chirp_period_s, hold_s;
  int64_t seed;
  double torque_amplitude_nm, torque_hold_s, delay_s, steer_rate_limit_rad_s, lateral_error_bound_m;
} program_t;

/* The dataclass defaults of ExcitationProgram. */
static program_t defaults(const char *name, int kind) {
  program_t p = {.kind = kind, .steer_amplitude_rad = 0.03, .lateral_accel_mps2 = 1.5, .wheelbase_m = 2.8,
                 .chirp_start_hz = 0.1, .chirp_end_hz = 2.0, .chirp_period_s = 40.0, .hold_s = 0.2, .seed = 0,
                 .torque_amplitude_nm = 0.0, .torque_hold_s = 1.0, .delay_s = 2.0,
                 .steer_rate_limit_rad_s = 0.5, .lateral_error_bound_m = 1.5};
  snprintf(p.name, sizeof p.name, "%s", name);
  return p;
}

static program_t program;
static int enabled;
static double table_time[ECU_EXCITE_TABLE_MAX], table_steer[ECU_EXCITE_TABLE_MAX], table_torque[ECU_EXCITE_TABLE_MAX];
static int table_rows, table_has_torque;
static char description[700];

/* One engagement's state (Excitation): start, applied offset, stop; e_Y's tracker. */
static int started, stopped, path_id = -1, has_progress;
static double started_s, steer_offset, progress;
static char stopped_reason[200];

/* ------------------------------------------------------------------ Python's arithmetic */
/* float.__floordiv__ as CPython computes it (float_floor_div). */
static double py_floordiv(double vx, double wx) {
  double mod = fmod(vx, wx), div = (vx - mod) / wx;
  if (mod != 0.0 && ((wx < 0) != (mod < 0))) div -= 1.0;
  if (div == 0.0) return copysign(0.0, vx / wx);
  double floordiv = floor(div);
  if (div - floordiv > 0.5) floordiv += 1.0;
  return floordiv;
}

/* float.__mod__ (the result takes the divisor's sign). */
static double py_mod(double vx, double wx) {
  double mod = fmod(vx, wx);
  if (mod != 0.0) {
    if ((wx < 0) != (mod < 0)) mod += wx;
  } else {
    mod = copysign(0.0, wx);
  }
  return mod;
}

/* repr(float): the shortest form that reads back, ".0" added to an integral one. */
static void py_repr(char *buf, size_t len, double v) {
  if (isnan(v)) {
    snprintf(buf, len, "nan");
    return;
  }
  if (isinf(v)) {
    snprintf(buf, len, v > 0 ? "inf" : "-inf");
    return;
  }
  int digits = 1;
  for (; digits < 17; digits++) { /* the fewest significant digits that read back */
    snprintf(buf, len, "%.*e", digits - 1, v);
    if (strtod(buf, NULL) == v) break;
  }
  snprintf(buf, len, "%.*e", digits - 1, v);
  const char *e = strchr(buf, 'e');
  int exponent = e ? atoi(e + 1) : 0;
  if (exponent < -4 || exponent >= 16) return; /* float_repr_style: 1e+308, 1.5e-05 */
  snprintf(buf, len, "%.*f", digits - 1 - exponent > 0 ? digits - 1 - exponent : 0, v);
  if (!strchr(buf, '.')) strncat(buf, ".0", len - strlen(buf) - 1);
}

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
static double steer_amplitude(double vx) {
  if (program.lateral_accel_mps2 == 0.0) return program.steer_amplitude_rad;
  double speed = fmax(fabs(vx), 1.0);
  double scaled = program.lateral_accel_mps2 * program.wheelbase_m / pow(speed, 2.0);
  return program.steer_amplitude_rad < scaled ? program.steer_amplitude_rad : scaled;
}

static double table_value(const double *values, double t) {
  if (!values || t < table_time[0] || t > table_time[table_rows - 1]) return 0.0;
  for (int k = 1; k < table_rows; k++) {
    if (t <= table_time[k]) {
      double share = (t - table_time[k - 1]) / (table_time[k] - table_time[k - 1]);
      return values[k - 1] + share * (values[k] - values[k - 1]);
    }
  }
  return values[table_rows - 1];
}

/* excitation_offsets: (steering offset, torque offset) time_active_s after entering ACTIVE.
 * -1 where Python's int() of a bit or step index would raise (an infinite quotient). */
static int offsets(double time_active_s, double vx, double *steer, double *torque) {
  double t = time_active_s - program.delay_s;
  *steer = *torque = 0.0;
  if (!isfinite(t) || t < 0.0) return 0;
  if (program.torque_amplitude_nm > 0.0) {
    double q = py_floordiv(t, program.torque_hold_s);
    if (!isfinite(q)) return -1;
    *torque = program.torque_amplitude_nm * prbs_bit(program.seed + 1, index_bits(q));
  }
  if (program.kind == TABLE) {
    *steer = table_value(table_steer, t);
    *torque = table_value(table_has_torque ? table_torque : NULL, t) + *torque;
    return 0;
  }
  double amplitude = steer_amplitude(vx);
  if (program.kind == CHIRP) {
    double tau = py_mod(t, program.chirp_period_s);
    double rate = (program.chirp_end_hz - program.chirp_start_hz) / program.chirp_period_s;
    double phase = 2.0 * PI * (program.chirp_start_hz * tau + 0.5 * rate * tau * tau);
    *steer = amplitude * sin(phase);
  } else {
    double q = py_floordiv(t, program.hold_s);
    if (!isfinite(q)) return -1;
    if (program.kind == PRBS) {
      *steer = amplitude * prbs_bit(program.seed, index_bits(q));
    } else {
      static const double STEPS[4] = {1.0, 0.0, -1.0, 0.0}; /* +, 0, -, 0 */
      *steer = amplitude * STEPS[index_bits(q) % 4u];
    }
  }
  return 0;
}

static double clip(double v, double lo, double hi) { return v < lo ? lo : (v > hi ? hi : v); }

/* ------------------------------------------------------------------ one engagement */
int ecu_excite_enabled(void) { return enabled; }

const char *ecu_excite_describe(void) { return description; }

void ecu_excite_reset(int new_path_id) {
  started = stopped = has_progress = 0;
  steer_offset = 0.0;
  stopped_reason[0] = '\0';
  path_id = new_path_id;
}

void ecu_excite_step(double now_s, int active, double vx, double x, double y, double *steer, double *torque,
                     double steer_min, double steer_max, double torque_min, double torque_max) {
  if (!enabled) return;
  if (!active) {
    steer_offset = 0.0;
    return;
  }
  double lateral_error = NAN;
  int known = ecu_path_pool_track(path_id, x, y, &progress, &has_progress, &lateral_error) == 0;
  if (!started) {
    started = 1;
    started_s = now_s;
  }
  double bound = program.lateral_error_bound_m;
  if (!stopped && known && !(fabs(lateral_error) <= bound)) {
    char value[40], limit[40];
    snprintf(value, sizeof value, "%.2f", fabs(lateral_error));
    py_repr(limit, sizeof limit, bound);
    snprintf(stopped_reason, sizeof stopped_reason, "|e_Y| = %s m > %s m", value, limit);
    stopped = 1;
    fprintf(stderr, "warning: excitation stopped for this engagement: %s\n", stopped_reason);
  }
  double target_steer = 0.0, torque_offset = 0.0;
  int failed = !stopped && isfinite(vx) ? offsets(now_s - started_s, vx, &target_steer, &torque_offset) : 0;
  if (failed == 0 && !(isfinite(target_steer) && isfinite(torque_offset))) failed = -2;
  if (failed != 0) {
    /* as the Python ECU when the program raises or its target is not finite: stopped, the
     * law's command this cycle */
    if (failed == -1) {
      snprintf(stopped_reason, sizeof stopped_reason, "excitation failed: a step index beyond any integer");
    } else {
      char a[40], b[40];
      py_repr(a, sizeof a, target_steer);
      py_repr(b, sizeof b, torque_offset);
      snprintf(stopped_reason, sizeof stopped_reason, "excitation failed: target not finite (steer %s, torque %s)",
               a, b);
    }
    stopped = 1;
    fprintf(stderr, "error: excitation stopped for this engagement: %s\n", stopped_reason);
    return;
  }
  double max_step = program.steer_rate_limit_rad_s * CONTROL_PERIOD_S;
  steer_offset = steer_offset + fmin(fmax(target_steer - steer_offset, -max_step), max_step);
  double s = *steer + steer_offset, q = *torque + torque_offset;
  *steer = isfinite(s) ? clip(s, steer_min, steer_max) : s;
  *torque = isfinite(q) ? clip(q, torque_min, torque_max) : q;
}

/* ------------------------------------------------------------------ loading */
/* ExcitationProgram.__post_init__ (its messages, "excitation program 'NAME': ..."). */
static int check_program(char *err, size_t err_len) {
  static const char *const POSITIVE[] = {"steer_amplitude_rad", "wheelbase_m", "chirp_start_hz", "chirp_end_hz",
                                         "chirp_period_s", "hold_s", "torque_hold_s", "steer_rate_limit_rad_s",
                                         "lateral_error_bound_m", "lateral_accel_mps2", "torque_amplitude_nm",
                                         "delay_s"};
  const double values[] = {program.steer_amplitude_rad, program.wheelbase_m, program.chirp_start_hz,
                           program.chirp_end_hz, program.chirp_period_s, program.hold_s, program.torque_hold_s,
                           program.steer_rate_limit_rad_s, program.lateral_error_bound_m,
                           program.lateral_accel_mps2, program.torque_amplitude_nm, program.delay_s};
  char where[NAME_BYTES + 40], shown[40];
  snprintf(where, sizeof where, "excitation program '%s'", program.name);
  for (int k = 0; k < 12; k++) {
    int positive = k < 9;
    if (!isfinite(values[k]) || values[k] < 0 || (positive && values[k] == 0)) {
      py_repr(shown, sizeof shown, values[k]);
      snprintf(err, err_len, "%s: %s must be a finite number %s, got %s", where, POSITIVE[k],
               positive ? "> 0" : ">= 0", shown);
      return -1;
    }
  }
  if (program.steer_amplitude_rad > STEER_LIMIT) {
    py_repr(shown, sizeof shown, program.steer_amplitude_rad);
    snprintf(err, err_len, "%s: steer_amplitude_rad %s exceeds the steering limit 0.3 rad", where, shown);
    return -1;
  }
  /* FIELD_LIMITS of excitation.py, in its order: every value bounded, so the step stays finite */
  static const char *const LIMITED[] = {"steer_amplitude_rad", "lateral_accel_mps2", "wheelbase_m",
                                        "chirp_start_hz", "chirp_end_hz", "chirp_period_s", "hold_s",
                                        "torque_hold_s", "torque_amplitude_nm", "delay_s",
                                        "steer_rate_limit_rad_s", "lateral_error_bound_m"};
  static const double LIMITS[] = {0.3, 20.0, 10.0, 20.0, 20.0, 3600.0, 3600.0, 3600.0, 3000.0, 3600.0, 10.0, 100.0};
  const double limited[] = {program.steer_amplitude_rad, program.lateral_accel_mps2, program.wheelbase_m,
                            program.chirp_start_hz, program.chirp_end_hz, program.chirp_period_s, program.hold_s,
                            program.torque_hold_s, program.torque_amplitude_nm, program.delay_s,
                            program.steer_rate_limit_rad_s, program.lateral_error_bound_m};
  for (int k = 0; k < 12; k++) {
    if (limited[k] > LIMITS[k]) {
      char limit[40];
      py_repr(shown, sizeof shown, limited[k]);
      py_repr(limit, sizeof limit, LIMITS[k]);
      snprintf(err, err_len, "%s: %s %s exceeds its limit %s", where, LIMITED[k], shown, limit);
      return -1;
    }
  }
  if (program.chirp_end_hz < program.chirp_start_hz) {
    char start[40];
    py_repr(shown, sizeof shown, program.chirp_end_hz);
    py_repr(start, sizeof start, program.chirp_start_hz);
    snprintf(err, err_len, "%s: chirp_end_hz %s < chirp_start_hz %s", where, shown, start);
    return -1;
  }
  if (program.kind != TABLE) return 0;
  if (table_rows < 2) {
    snprintf(err, err_len, "%s: a table needs at least 2 rows, got %d", where, table_rows);
    return -1;
  }
  double largest = 0.0;
  for (int i = 0; i < table_rows; i++) {
    if (!isfinite(table_time[i]) || !isfinite(table_steer[i]) || (table_has_torque && !isfinite(table_torque[i]))) {
      snprintf(err, err_len, "%s: table holds a value that is not finite", where);
      return -1;
    }
  }
  for (int i = 1; i < table_rows; i++) {
    if (table_time[i] <= table_time[i - 1]) {
      snprintf(err, err_len, "%s: table time_s must increase strictly", where);
      return -1;
    }
  }
  double latest = 0.0, strongest = 0.0;
  for (int i = 0; i < table_rows; i++) {
    largest = fmax(largest, fabs(table_steer[i]));
    latest = fmax(latest, fabs(table_time[i]));
    if (table_has_torque) strongest = fmax(strongest, fabs(table_torque[i]));
  }
  if (largest > STEER_LIMIT) {
    snprintf(err, err_len, "%s: table steer_rad exceeds the steering limit 0.3 rad", where);
    return -1;
  }
  if (latest > TABLE_TIME_LIMIT_S) {
    snprintf(err, err_len, "%s: table time_s exceeds its limit 86400.0 s in magnitude", where);
    return -1;
  }
  if (strongest > TABLE_TORQUE_LIMIT_NM) {
    snprintf(err, err_len, "%s: table torque_nm exceeds its limit 3000.0 N m in magnitude", where);
    return -1;
  }
  return 0;
}

static char *trim(char *text) {
  while (isspace((unsigned char)*text)) text++;
  char *end = text + strlen(text);
  while (end > text && isspace((unsigned char)end[-1])) *--end = '\0';
  return text;
}

/* float(text) for a decimal number, nan or inf; 0 when it is not one. */
static int parse_float(const char *text, double *value) {
  char *end;
  if (!*text) return 0;
  *value = strtod(text, &end);
  return *end == '\0' && !strpbrk(text, "xX");
}

/* The file name without folder and extension (Path.stem). */
static void stem_of(const char *file, char *stem, size_t len) {
  const char *base = strrchr(file, '/');
  base = base ? base + 1 : file;
  snprintf(stem, len, "%s", base);
  char *dot = strrchr(stem, '.');
  if (dot && dot != stem) *dot = '\0';
}

static int load_table(const char *file, ecu_lines_t *lines, char *err, size_t err_len) {
  static char line[LINE_BYTES];
  int number = 0, columns = 0, got;
  table_rows = 0;
  while ((got = ecu_read_line(lines, line, err, err_len)) != 0) {
    if (got < 0) return -1;
    number++;
    char *cells[4];
    int count = 0;
    for (char *cursor = line; count < 4;) {
      cells[count++] = cursor;
      char *comma = strchr(cursor, ',');
      if (!comma) break;
      *comma = '\0';
      cursor = comma + 1;
    }
    if (number == 1) {
      int two = count == 2 && !strcmp(trim(cells[0]), "time_s") && !strcmp(trim(cells[1]), "steer_rad");
      int three = count == 3 && !strcmp(trim(cells[0]), "time_s") && !strcmp(trim(cells[1]), "steer_rad") &&
                  !strcmp(trim(cells[2]), "torque_nm");
      if (!two && !three) {
        char got[200] = "";
        for (int j = 0; j < count && j < 3; j++)
          snprintf(got + strlen(got), sizeof got - strlen(got), j ? ",%s" : "%s", trim(cells[j]));
        snprintf(err, err_len, "--excite %s: line 1: header must be time_s,steer_rad[,torque_nm], got '%s%s'", file,
                 got, count > 3 ? ",..." : "");
        return -1;
      }
      columns = count;
      table_has_torque = three;
      continue;
    }
    int blank = 1;
    for (int j = 0; j < count; j++) blank = blank && !*trim(cells[j]);
    if (blank) continue;
    if (count != columns) {
      snprintf(err, err_len, "--excite %s: line %d: expected %d values, got %d%s", file, number, columns, count,
               count > 3 ? " or more" : "");
      return -1;
    }
    if (table_rows == ECU_EXCITE_TABLE_MAX) {
      snprintf(err, err_len, "--excite %s: line %d: more than %d rows (the table limit of both ECUs)", file, number,
               ECU_EXCITE_TABLE_MAX);
      return -1;
    }
    double *targets[3] = {&table_time[table_rows], &table_steer[table_rows], &table_torque[table_rows]};
    for (int j = 0; j < count; j++) {
      if (!parse_float(trim(cells[j]), targets[j])) {
        snprintf(err, err_len, "--excite %s: line %d: not a number in column %d", file, number, j + 1);
        return -1;
      }
    }
    table_rows++;
  }
  if (number == 0) {
    snprintf(err, err_len, "--excite %s: line 1: header must be time_s,steer_rad[,torque_nm], got ''", file);
    return -1;
  }
  return 0;
}

/* The TOML reader: `key = value` lines (a number, true / false, or a "string"), comments.
 * Tables and arrays are not ExcitationProgram fields; they are refused by name. */
static int load_toml(const char *file, ecu_lines_t *lines, char *err, size_t err_len) {
  static const char *const FIELDS[] = {"name", "kind", "steer_amplitude_rad", "lateral_accel_mps2", "wheelbase_m",
                                       "chirp_start_hz", "chirp_end_hz", "chirp_period_s", "hold_s", "seed",
                                       "torque_amplitude_nm", "torque_hold_s", "delay_s", "steer_rate_limit_rad_s",
                                       "lateral_error_bound_m", "table_time_s", "table_steer_rad", "table_torque_nm"};
  enum { N_FIELDS = sizeof FIELDS / sizeof FIELDS[0] };
  static char line[LINE_BYTES];
  char kind[NAME_BYTES] = "", name[NAME_BYTES];
  int number = 0, has_kind = 0, got;
  int64_t program_seed = 0;
  double numbers[N_FIELDS];
  int given[N_FIELDS] = {0};
  stem_of(file, name, sizeof name);
  while ((got = ecu_read_line(lines, line, err, err_len)) != 0) {
    if (got < 0) return -1;
    number++;
    char *text = trim(line);
    if (!*text || *text == '#') continue;
    char *equals = strchr(text, '=');
    if (*text == '[' || !equals) {
      snprintf(err, err_len, "--excite %s: line %d: the C ECU reads `key = value` lines only (no tables)", file,
               number);
      return -1;
    }
    *equals = '\0';
    char *key = trim(text), *value = trim(equals + 1);
    int field = -1;
    for (int k = 0; k < N_FIELDS; k++)
      if (!strcmp(key, FIELDS[k])) field = k;
    if (field < 0) {
      char known[600] = "";
      for (int k = 0; k < N_FIELDS; k++)
        snprintf(known + strlen(known), sizeof known - strlen(known), k ? ", %s" : "%s", FIELDS[k]);
      snprintf(err, err_len, "--excite %s: unknown field(s) %s; known: %s", file, key, known);
      return -1;
    }
    if (!strncmp(key, "table_", 6)) {
      snprintf(err, err_len, "--excite %s: field %s belongs in a CSV table program", file, key);
      return -1;
    }
    if (*value == '"') { /* a basic string without escapes, then an optional comment */
      char *close = strchr(value + 1, '"');
      char *rest = close ? trim(close + 1) : NULL;
      if (!close || strchr(value + 1, '\\') || (*rest && *rest != '#')) {
        snprintf(err, err_len, "--excite %s: line %d: not valid TOML (a string without escapes expected)", file,
                 number);
        return -1;
      }
      *close = '\0';
      if (field != 0 && field != 1) {
        snprintf(err, err_len, "excitation program '%s': %s must be a finite number, got '%s'", name, key,
                 value + 1);
        return -1;
      }
      snprintf(field == 0 ? name : kind, NAME_BYTES, "%s", value + 1);
      has_kind |= field == 1;
      continue;
    }
    char *comment = strchr(value, '#');
    if (comment) *comment = '\0';
    value = trim(value);
    double parsed;
    if (!strcmp(value, "true") || !strcmp(value, "false")) {
      snprintf(err, err_len, "--excite %s: field %s must be %s, got %s", file, key,
               field == 9 ? "an integer" : "a finite number", value[0] == 't' ? "True" : "False");
      return -1;
    }
    const char *number_text = !strcmp(value, "+inf") ? "inf" : (!strcmp(value, "+nan") ? "nan" : value);
    if (field <= 1 || !parse_float(number_text, &parsed)) {
      snprintf(err, err_len, "--excite %s: line %d: %s = %s: not a value the C ECU reads (a number, or a \"string\" "
               "for name and kind)", file, number, key, value);
      return -1;
    }
    if (field == 9 && (strpbrk(value, ".eEn") || parsed != floor(parsed))) {
      snprintf(err, err_len, "--excite %s: field seed must be an integer, got %s", file, value);
      return -1;
    }
    if (field == 9) { /* exact as an integer (a double would round a large seed) */
      char *end;
      errno = 0;
      long long seed = strtoll(value, &end, 10);
      if (errno == ERANGE || *end != '\0' || seed == LLONG_MAX || seed == LLONG_MIN) {
        snprintf(err, err_len, "excitation program '%s': seed %s must be an integer of magnitude below 2^63 - 1",
                 name, value);
        return -1;
      }
      program_seed = (int64_t)seed;
    }
    numbers[field] = parsed;
    given[field] = 1;
  }
  if (!has_kind) {
    snprintf(err, err_len, "--excite %s: field 'kind' missing (one of chirp, prbs, steps)", file);
    return -1;
  }
  if (!strcmp(kind, "table")) {
    snprintf(err, err_len, "--excite %s: a table program is a CSV file time_s,steer_rad[,torque_nm]", file);
    return -1;
  }
  int kind_id = -1;
  for (int k = 0; k < 3; k++)
    if (!strcmp(kind, KIND_NAMES[k])) kind_id = k;
  if (kind_id < 0) {
    snprintf(err, err_len, "excitation program '%s': kind '%s' is not one of chirp, prbs, steps, table", name, kind);
    return -1;
  }
  program = defaults(name, kind_id);
  double *targets[N_FIELDS] = {NULL, NULL, &program.steer_amplitude_rad, &program.lateral_accel_mps2,
                               &program.wheelbase_m, &program.chirp_start_hz, &program.chirp_end_hz,
                               &program.chirp_period_s, &program.hold_s, NULL, &program.torque_amplitude_nm,
                               &program.torque_hold_s, &program.delay_s, &program.steer_rate_limit_rad_s,
                               &program.lateral_error_bound_m};
  for (int k = 2; k < 15; k++)
    if (given[k] && targets[k]) *targets[k] = numbers[k];
  if (given[9]) program.seed = program_seed;
  return 0;
}

static void describe(void) {
  char a[40], b[40], c[40], d[40], e[40], f[40], g[40];
  if (program.kind == TABLE) {
    snprintf(description, sizeof description, "excitation %s: table of %d rows over %.1f s", program.name, table_rows,
             table_time[table_rows - 1] - table_time[0]);
    return;
  }
  char band[160], torque[80] = "";
  py_repr(a, sizeof a, program.chirp_start_hz);
  py_repr(b, sizeof b, program.chirp_end_hz);
  py_repr(c, sizeof c, program.chirp_period_s);
  py_repr(d, sizeof d, program.hold_s);
  if (program.kind == CHIRP) snprintf(band, sizeof band, "%s-%s Hz sweep over %s s", a, b, c);
  else if (program.kind == PRBS) snprintf(band, sizeof band, "PRBS, bit %s s", d);
  else snprintf(band, sizeof band, "steps of %s s", d);
  if (program.torque_amplitude_nm != 0.0) {
    py_repr(e, sizeof e, program.torque_amplitude_nm);
    snprintf(torque, sizeof torque, ", torque PRBS +-%s N m", e);
  }
  py_repr(a, sizeof a, program.lateral_accel_mps2);
  py_repr(b, sizeof b, program.steer_amplitude_rad);
  py_repr(f, sizeof f, program.delay_s);
  py_repr(g, sizeof g, program.lateral_error_bound_m);
  snprintf(description, sizeof description,
           "excitation %s: %s, %s m/s^2 up to %s rad%s, from %s s after ACTIVE, stops at |e_Y| > %s m", program.name,
           band, a, b, torque, f, g);
}

int ecu_excite_is_file(const char *spec) {
  return strcmp(spec, "chirp") && strcmp(spec, "prbs") && strcmp(spec, "steps") && strcmp(spec, "prbs-torque");
}

int ecu_excite_load(const char *spec, char *err, size_t err_len) {
  enabled = 0;
  table_rows = table_has_torque = 0;
  if (!strcmp(spec, "chirp")) {
    program = defaults("chirp", CHIRP);
  } else if (!strcmp(spec, "prbs")) {
    program = defaults("prbs", PRBS);
  } else if (!strcmp(spec, "steps")) {
    program = defaults("steps", STEPS);
    program.hold_s = 2.0;
  } else if (!strcmp(spec, "prbs-torque")) {
    program = defaults("prbs-torque", PRBS);
    program.torque_amplitude_nm = 300.0;
  } else {
    const char *dot = strrchr(spec, '.');
    const char *slash = strrchr(spec, '/');
    char suffix[8] = "";
    if (dot && (!slash || dot > slash + 1) && strlen(dot) < sizeof suffix)
      for (size_t k = 0; k <= strlen(dot); k++) suffix[k] = (char)tolower((unsigned char)dot[k]);
    int csv = !strcmp(suffix, ".csv");
    if (!csv && strcmp(suffix, ".toml")) {
      snprintf(err, err_len, "--excite '%s': not a shipped program (chirp, prbs, steps, prbs-torque) nor a .toml / "
               ".csv program file", spec);
      return -1;
    }
    FILE *stream = fopen(spec, "r");
    if (!stream) {
      snprintf(err, err_len, "--excite %s: cannot read: %s", spec, strerror(errno));
      return -1;
    }
    char name[NAME_BYTES], option[NAME_BYTES + 300];
    stem_of(spec, name, sizeof name);
    snprintf(option, sizeof option, "--excite %s", spec);
    ecu_lines_t lines = {.name = option, .stream = stream, .max_bytes = ECU_EXCITE_FILE_MAX};
    int status = csv ? load_table(spec, &lines, err, err_len) : load_toml(spec, &lines, err, err_len);
    fclose(stream);
    if (status != 0) return -1;
    if (csv) program = defaults(name, TABLE);
  }
  if (check_program(err, err_len) != 0) return -1;
  describe();
  enabled = 1;
  ecu_excite_reset(-1);
  return 0;
}
