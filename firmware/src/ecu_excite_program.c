/*
 * Loading an excitation program (see ecu_excite.h): the shipped ones, a .toml file of
 * ExcitationProgram's fields or a .csv table, checked as ExcitationProgram.__post_init__
 * with its messages.
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
#include "ecu_pyfloat.h"

#define STEER_LIMIT 0.3 /* rad: a program's amplitude may not exceed the command limit */
#define LINE_BYTES (ECU_LINE_MAX + 2)
#define NAME_BYTES ((int)sizeof(((ecu_excite_program_t *)0)->name))
#define TABLE_TIME_LIMIT_S 86400.0  /* |time_s| of a table row (excitation.py TABLE_TIME_LIMIT_S) */
#define TABLE_TORQUE_LIMIT_NM 3000.0 /* |torque_nm| of a table row */

static const char *const KIND_NAMES[] = {"chirp", "prbs", "steps", "table"};

/* The dataclass defaults of ExcitationProgram. */
static ecu_excite_program_t defaults(const char *name, int kind) {
  ecu_excite_program_t p = {.kind = kind, .steer_amplitude_rad = 0.03, .lateral_accel_mps2 = 1.5, .wheelbase_m = 2.8,
                 .chirp_start_hz = 0.1, .chirp_end_hz = 2.0, .chirp_period_s = 40.0, .hold_s = 0.2, .seed = 0,
                 .torque_amplitude_nm = 0.0, .torque_hold_s = 1.0, .delay_s = 2.0,
                 .steer_rate_limit_rad_s = 0.5, .lateral_error_bound_m = 1.5};
  snprintf(p.name, sizeof p.name, "%s", name);
  return p;
}

/* ExcitationProgram.__post_init__ (its messages, "excitation program 'NAME': ..."). */
static int check_program(ecu_excite_t *ex, char *err, size_t err_len) {
  static const char *const POSITIVE[] = {"steer_amplitude_rad", "wheelbase_m", "chirp_start_hz", "chirp_end_hz",
                                         "chirp_period_s", "hold_s", "torque_hold_s", "steer_rate_limit_rad_s",
                                         "lateral_error_bound_m", "lateral_accel_mps2", "torque_amplitude_nm",
                                         "delay_s"};
  const double values[] = {ex->program.steer_amplitude_rad, ex->program.wheelbase_m, ex->program.chirp_start_hz,
                           ex->program.chirp_end_hz, ex->program.chirp_period_s, ex->program.hold_s, ex->program.torque_hold_s,
                           ex->program.steer_rate_limit_rad_s, ex->program.lateral_error_bound_m,
                           ex->program.lateral_accel_mps2, ex->program.torque_amplitude_nm, ex->program.delay_s};
  char where[NAME_BYTES + 40], shown[40];
  snprintf(where, sizeof where, "excitation program '%s'", ex->program.name);
  for (int k = 0; k < 12; k++) {
    int positive = k < 9;
    if (!isfinite(values[k]) || values[k] < 0 || (positive && values[k] == 0)) {
      py_repr(shown, sizeof shown, values[k]);
      snprintf(err, err_len, "%s: %s must be a finite number %s, got %s", where, POSITIVE[k],
               positive ? "> 0" : ">= 0", shown);
      return -1;
    }
  }
  if (ex->program.steer_amplitude_rad > STEER_LIMIT) {
    py_repr(shown, sizeof shown, ex->program.steer_amplitude_rad);
    snprintf(err, err_len, "%s: steer_amplitude_rad %s exceeds the steering limit 0.3 rad", where, shown);
    return -1;
  }
  /* FIELD_LIMITS of excitation.py, in its order: every value bounded, so the step stays finite */
  static const char *const LIMITED[] = {"steer_amplitude_rad", "lateral_accel_mps2", "wheelbase_m",
                                        "chirp_start_hz", "chirp_end_hz", "chirp_period_s", "hold_s",
                                        "torque_hold_s", "torque_amplitude_nm", "delay_s",
                                        "steer_rate_limit_rad_s", "lateral_error_bound_m"};
  static const double LIMITS[] = {0.3, 20.0, 10.0, 20.0, 20.0, 3600.0, 3600.0, 3600.0, 3000.0, 3600.0, 10.0, 100.0};
  const double limited[] = {ex->program.steer_amplitude_rad, ex->program.lateral_accel_mps2, ex->program.wheelbase_m,
                            ex->program.chirp_start_hz, ex->program.chirp_end_hz, ex->program.chirp_period_s, ex->program.hold_s,
                            ex->program.torque_hold_s, ex->program.torque_amplitude_nm, ex->program.delay_s,
                            ex->program.steer_rate_limit_rad_s, ex->program.lateral_error_bound_m};
  for (int k = 0; k < 12; k++) {
    if (limited[k] > LIMITS[k]) {
      char limit[40];
      py_repr(shown, sizeof shown, limited[k]);
      py_repr(limit, sizeof limit, LIMITS[k]);
      snprintf(err, err_len, "%s: %s %s exceeds its limit %s", where, LIMITED[k], shown, limit);
      return -1;
    }
  }
  if (ex->program.chirp_end_hz < ex->program.chirp_start_hz) {
    char start[40];
    py_repr(shown, sizeof shown, ex->program.chirp_end_hz);
    py_repr(start, sizeof start, ex->program.chirp_start_hz);
    snprintf(err, err_len, "%s: chirp_end_hz %s < chirp_start_hz %s", where, shown, start);
    return -1;
  }
  if (ex->program.kind != ECU_EXCITE_TABLE) return 0;
  if (ex->table_rows < 2) {
    snprintf(err, err_len, "%s: a table needs at least 2 rows, got %d", where, ex->table_rows);
    return -1;
  }
  double largest = 0.0;
  for (int i = 0; i < ex->table_rows; i++) {
    if (!isfinite(ex->table_time[i]) || !isfinite(ex->table_steer[i]) || (ex->table_has_torque && !isfinite(ex->table_torque[i]))) {
      snprintf(err, err_len, "%s: table holds a value that is not finite", where);
      return -1;
    }
  }
  for (int i = 1; i < ex->table_rows; i++) {
    if (ex->table_time[i] <= ex->table_time[i - 1]) {
      snprintf(err, err_len, "%s: table time_s must increase strictly", where);
      return -1;
    }
  }
  double latest = 0.0, strongest = 0.0;
  for (int i = 0; i < ex->table_rows; i++) {
    largest = fmax(largest, fabs(ex->table_steer[i]));
    latest = fmax(latest, fabs(ex->table_time[i]));
    if (ex->table_has_torque) strongest = fmax(strongest, fabs(ex->table_torque[i]));
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

/* Digits with single underscores between them (TOML's 1*( DIGIT / "_" DIGIT )) from *text,
 * copied to plain[*used] without the underscores; *text moves past them. 0: no digit. */
static int toml_digits(const char **text, char *plain, size_t *used) {
  const char *p = *text;
  if (!isdigit((unsigned char)*p)) return 0;
  while (isdigit((unsigned char)*p) || (*p == '_' && isdigit((unsigned char)p[1]))) {
    if (*p != '_') plain[(*used)++] = *p;
    p++;
  }
  *text = p;
  return 1;
}

/* A TOML hexadecimal, octal or binary integer's digits (after 0x / 0o / 0b, underscores
 * between them) into plain as a decimal integer, saturated at LLONG_MAX (over every field's
 * limit, as the unbounded Python int is). 0: not such digits. */
static int toml_radix_integer(const char *digits, int base, char *plain, size_t len) {
  static const char DIGITS[] = "0123456789abcdef";
  unsigned long long value = 0;
  const char *p = digits;
  for (;; p++) {
    const char *at = *p ? strchr(DIGITS, tolower((unsigned char)*p)) : NULL;
    int digit = at && at - DIGITS < base ? (int)(at - DIGITS) : -1;
    if (digit < 0 && *p == '_' && p > digits && p[1] && p[-1] != '_') continue; /* checked below */
    if (digit < 0) break;
    value = value > (LLONG_MAX - (unsigned long long)digit) / (unsigned long long)base
                ? (unsigned long long)LLONG_MAX
                : value * (unsigned long long)base + (unsigned long long)digit;
  }
  if (p == digits || *p != '\0' || p[-1] == '_') return 0;
  snprintf(plain, len, "%llu", value);
  return 1;
}

/* A TOML number (integer or float, as Python's tomllib reads it) into plain (len >=
 * strlen(text) + 1) as decimal text without underscores, for strtod / strtoll: 0x / 0o /
 * 0b and the integer's digits; or an optional sign, then inf or nan, or an integer part
 * with no leading zero, an optional fraction with a digit on each side of its point and an
 * optional exponent. 0 for anything else (".5", "5.", "05", "1__0", "infinity"), which
 * tomllib refuses too. */
static int toml_number(const char *text, char *plain, size_t len) {
  size_t used = 0;
  if (strlen(text) >= len) return 0;
  if (text[0] == '0' && text[1] && strchr("xob", text[1])) /* no sign before these in TOML */
    return toml_radix_integer(text + 2, text[1] == 'x' ? 16 : (text[1] == 'o' ? 8 : 2), plain, len);
  if (*text == '+' || *text == '-') plain[used++] = *text++;
  if (!strcmp(text, "inf") || !strcmp(text, "nan")) {
    snprintf(plain + used, len - used, "%s", text);
    return 1;
  }
  if (text[0] == '0' && (isdigit((unsigned char)text[1]) || text[1] == '_')) return 0;
  if (!toml_digits(&text, plain, &used)) return 0;
  if (*text == '.') {
    plain[used++] = *text++;
    if (!toml_digits(&text, plain, &used)) return 0;
  }
  if (*text == 'e' || *text == 'E') {
    plain[used++] = *text++;
    if (*text == '+' || *text == '-') plain[used++] = *text++;
    if (!toml_digits(&text, plain, &used)) return 0;
  }
  plain[used] = '\0';
  return *text == '\0';
}

/* The file name without folder and extension (Path.stem). */
static void stem_of(const char *file, char *stem, size_t len) {
  const char *base = strrchr(file, '/');
  base = base ? base + 1 : file;
  snprintf(stem, len, "%s", base);
  char *dot = strrchr(stem, '.');
  if (dot && dot != stem) *dot = '\0';
}

static int load_table(ecu_excite_t *ex, const char *file, ecu_lines_t *lines, char *err, size_t err_len) {
  static char line[LINE_BYTES];
  int number = 0, columns = 0, got;
  ex->table_rows = 0;
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
      ex->table_has_torque = three;
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
    if (ex->table_rows == ECU_EXCITE_TABLE_MAX) {
      snprintf(err, err_len, "--excite %s: line %d: more than %d rows (the table limit of both ECUs)", file, number,
               ECU_EXCITE_TABLE_MAX);
      return -1;
    }
    double *targets[3] = {&ex->table_time[ex->table_rows], &ex->table_steer[ex->table_rows], &ex->table_torque[ex->table_rows]};
    for (int j = 0; j < count; j++) {
      if (!parse_float(trim(cells[j]), targets[j])) {
        snprintf(err, err_len, "--excite %s: line %d: not a number in column %d: '%s'", file, number, j + 1,
                 trim(cells[j]));
        return -1;
      }
    }
    ex->table_rows++;
  }
  if (number == 0) {
    snprintf(err, err_len, "--excite %s: line 1: header must be time_s,steer_rad[,torque_nm], got ''", file);
    return -1;
  }
  return 0;
}

/* The TOML reader: `key = value` lines (a number, true / false, or a "string"), comments.
 * Tables and arrays are not ExcitationProgram fields; they are refused by name. */
static int load_toml(ecu_excite_t *ex, const char *file, ecu_lines_t *lines, char *err, size_t err_len) {
  static const char *const FIELDS[] = {"name", "kind", "steer_amplitude_rad", "lateral_accel_mps2", "wheelbase_m",
                                       "chirp_start_hz", "chirp_end_hz", "chirp_period_s", "hold_s", "seed",
                                       "torque_amplitude_nm", "torque_hold_s", "delay_s", "steer_rate_limit_rad_s",
                                       "lateral_error_bound_m", "table_time_s", "table_steer_rad", "table_torque_nm"};
  enum { N_FIELDS = sizeof FIELDS / sizeof FIELDS[0] };
  static char line[LINE_BYTES], plain[LINE_BYTES]; /* start-up only: one program is read */
  char kind[NAME_BYTES] = "", name[NAME_BYTES];
  int number = 0, has_kind = 0, got;
  int64_t program_seed = 0;
  double numbers[N_FIELDS];
  int given[N_FIELDS] = {0}, seen[N_FIELDS] = {0};
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
    if (seen[field]) { /* TOML defines a key once; tomllib refuses the file */
      snprintf(err, err_len, "--excite %s: line %d: not valid TOML (%s given twice)", file, number, key);
      return -1;
    }
    seen[field] = 1;
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
    if (field <= 1 || !toml_number(value, plain, sizeof plain) || !parse_float(plain, &parsed)) {
      snprintf(err, err_len, "--excite %s: line %d: %s = %s: not a value the C ECU reads (a number, or a \"string\" "
               "for name and kind)", file, number, key, value);
      return -1;
    }
    if (field == 9 && (strpbrk(plain, ".eEn") || parsed != floor(parsed))) {
      snprintf(err, err_len, "--excite %s: field seed must be an integer, got %s", file, value);
      return -1;
    }
    if (field == 9) { /* exact as an integer (a double would round a large seed) */
      char *end;
      errno = 0;
      long long seed = strtoll(plain, &end, 10);
      if (errno == ERANGE || *end != '\0' || seed == LLONG_MAX || seed == LLONG_MIN) {
        snprintf(err, err_len, "excitation program '%s': seed %s must be an integer of magnitude below 2^63 - 1",
                 name, plain);
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
  ex->program = defaults(name, kind_id);
  double *targets[N_FIELDS] = {NULL, NULL, &ex->program.steer_amplitude_rad, &ex->program.lateral_accel_mps2,
                               &ex->program.wheelbase_m, &ex->program.chirp_start_hz, &ex->program.chirp_end_hz,
                               &ex->program.chirp_period_s, &ex->program.hold_s, NULL, &ex->program.torque_amplitude_nm,
                               &ex->program.torque_hold_s, &ex->program.delay_s, &ex->program.steer_rate_limit_rad_s,
                               &ex->program.lateral_error_bound_m};
  for (int k = 2; k < 15; k++)
    if (given[k] && targets[k]) *targets[k] = numbers[k];
  if (given[9]) ex->program.seed = program_seed;
  return 0;
}

static void describe(ecu_excite_t *ex) {
  char a[40], b[40], c[40], d[40], e[40], f[40], g[40];
  if (ex->program.kind == ECU_EXCITE_TABLE) {
    snprintf(ex->description, sizeof ex->description, "excitation %s: table of %d rows over %.1f s", ex->program.name, ex->table_rows,
             ex->table_time[ex->table_rows - 1] - ex->table_time[0]);
    return;
  }
  char band[160], torque[80] = "";
  py_repr(a, sizeof a, ex->program.chirp_start_hz);
  py_repr(b, sizeof b, ex->program.chirp_end_hz);
  py_repr(c, sizeof c, ex->program.chirp_period_s);
  py_repr(d, sizeof d, ex->program.hold_s);
  if (ex->program.kind == ECU_EXCITE_CHIRP) snprintf(band, sizeof band, "%s-%s Hz sweep over %s s", a, b, c);
  else if (ex->program.kind == ECU_EXCITE_PRBS) snprintf(band, sizeof band, "PRBS, bit %s s", d);
  else snprintf(band, sizeof band, "steps of %s s", d);
  if (ex->program.torque_amplitude_nm != 0.0) {
    py_repr(e, sizeof e, ex->program.torque_amplitude_nm);
    snprintf(torque, sizeof torque, ", torque PRBS +-%s N m", e);
  }
  py_repr(a, sizeof a, ex->program.lateral_accel_mps2);
  py_repr(b, sizeof b, ex->program.steer_amplitude_rad);
  py_repr(f, sizeof f, ex->program.delay_s);
  py_repr(g, sizeof g, ex->program.lateral_error_bound_m);
  snprintf(ex->description, sizeof ex->description,
           "excitation %s: %s, %s m/s^2 up to %s rad%s, from %s s after ACTIVE, stops at |e_Y| > %s m", ex->program.name,
           band, a, b, torque, f, g);
}

int ecu_excite_is_file(const char *spec) {
  return strcmp(spec, "chirp") && strcmp(spec, "prbs") && strcmp(spec, "steps") && strcmp(spec, "prbs-torque");
}

int ecu_excite_load(ecu_excite_t *ex, const char *spec, char *err, size_t err_len) {
  ex->enabled = 0;
  ex->table_rows = ex->table_has_torque = 0;
  if (!strcmp(spec, "chirp")) {
    ex->program = defaults("chirp", ECU_EXCITE_CHIRP);
  } else if (!strcmp(spec, "prbs")) {
    ex->program = defaults("prbs", ECU_EXCITE_PRBS);
  } else if (!strcmp(spec, "steps")) {
    ex->program = defaults("steps", ECU_EXCITE_STEPS);
    ex->program.hold_s = 2.0;
  } else if (!strcmp(spec, "prbs-torque")) {
    ex->program = defaults("prbs-torque", ECU_EXCITE_PRBS);
    ex->program.torque_amplitude_nm = 300.0;
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
    int status = csv ? load_table(ex, spec, &lines, err, err_len) : load_toml(ex, spec, &lines, err, err_len);
    fclose(stream);
    if (status != 0) return -1;
    if (csv) ex->program = defaults(name, ECU_EXCITE_TABLE);
  }
  if (check_program(ex, err, err_len) != 0) return -1;
  describe(ex);
  ex->enabled = 1;
  ecu_excite_reset(ex, -1);
  return 0;
}
