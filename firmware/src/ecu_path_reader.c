/*
 * Path files into the pool (see ecu_path_reader.h). The file is read line by line and
 * refused at its 100,001st point. Differences from Python's csv and float(): a quoted cell
 * may not contain a comma, and numbers with underscores ("1_000") or hexadecimal floats
 * are refused.
 */
#include <ctype.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ecu_lines.h"
#include "ecu_path_reader.h"

#define PI 3.141592653589793
#define TWO_PI 6.283185307179586
#define MIN_FILE_POINT_SPACING 0.01 /* m */
#define MAX_POINT_SPACING 0.5       /* m */
#define MAX_YAW_DEVIATION 0.5       /* rad */
#define MAX_SEGMENT_TURN 0.5        /* rad */
#define POSITION_MIN (-8388.608)    /* m: the range of POS_X / POS_Y */
#define POSITION_MAX 8388.607
#define LINE_BYTES (ECU_LINE_MAX + 2)

static const char *const HEADER[3] = {"x", "y", "yaw"};

/* The points of the file being read: the free end of the pool. */
typedef struct {
  double *x, *y, *yaw, *s;
  int *line;
} points_t;

/* Python's a % b for b > 0 (the result takes b's sign). */
static double py_mod(double a, double b) {
  double m = fmod(a, b);
  if (m != 0.0 && m < 0.0) m += b;
  return m == 0.0 ? 0.0 : m;
}

/* models.measurement.wrap_angle: to [-pi, pi), values inside unchanged bit for bit. */
static double wrap_angle(double a) { return (a >= -PI && a < PI) ? a : py_mod(a + PI, TWO_PI) - PI; }

/* |a - b| modulo 2 pi, in [0, pi] (reference._angle_difference). */
static double angle_difference(double a, double b) { return fabs(py_mod(a - b + PI, TWO_PI) - PI); }

/* Strip blanks, then one pair of surrounding double quotes (csv's quoting). */
static char *trim(char *cell) {
  size_t n;
  while (isspace((unsigned char)*cell)) cell++;
  n = strlen(cell);
  while (n > 0 && isspace((unsigned char)cell[n - 1])) cell[--n] = '\0';
  if (n >= 2 && cell[0] == '"' && cell[n - 1] == '"') {
    cell[n - 1] = '\0';
    cell++;
  }
  return cell;
}

/* A cell as Python's float() reads it: decimal, inf, nan; 0 and *ok = 0 otherwise. */
static double parse_number(char *text, int *ok) {
  char *end, *cell = trim(text);
  *ok = 0;
  if (*cell == '\0' || strpbrk(cell, "xX_")) return 0.0;
  double value = strtod(cell, &end);
  if (*end != '\0') return 0.0;
  *ok = 1;
  return value;
}

/* Python's repr of a finite or non-finite float as the message shows it. */
static void format_float(char *buf, size_t len, double v) {
  if (isnan(v)) snprintf(buf, len, "nan");
  else if (isinf(v)) snprintf(buf, len, v > 0 ? "inf" : "-inf");
  else snprintf(buf, len, "%.17g", v);
}

static int check_points(const points_t *p, const char *where, int n, char *err, size_t err_len) {
  const double *px = p->x, *py = p->y, *pyaw = p->yaw;
  const int *line_of = p->line;
  char value[64];
  if (n < 2) {
    snprintf(err, err_len, "%s: needs at least 2 points, got %d", where, n);
    return -1;
  }
  for (int i = 0; i < n; i++) {
    const double v[3] = {px[i], py[i], pyaw[i]};
    for (int j = 0; j < 3; j++)
      if (!isfinite(v[j])) {
        format_float(value, sizeof value, v[j]);
        snprintf(err, err_len, "%s: line %d: %s = %s is not finite", where, line_of[i], HEADER[j], value);
        return -1;
      }
  }
  for (int i = 0; i < n; i++) {
    const double v[2] = {px[i], py[i]};
    for (int j = 0; j < 2; j++)
      if (v[j] < POSITION_MIN || v[j] > POSITION_MAX) {
        snprintf(err, err_len, "%s: line %d: %s = %g m is outside the range of POS_X / POS_Y [-8388.608, 8388.607] m",
                 where, line_of[i], HEADER[j], v[j]);
        return -1;
      }
  }
  for (int i = 0; i + 1 < n; i++) {
    double spacing = hypot(px[i + 1] - px[i], py[i + 1] - py[i]);
    if (spacing < MIN_FILE_POINT_SPACING || spacing > MAX_POINT_SPACING) {
      snprintf(err, err_len, "%s: line %d: %.3f m from the previous point (must be %g to %g m)", where,
               line_of[i + 1], spacing, MIN_FILE_POINT_SPACING, MAX_POINT_SPACING);
      return -1;
    }
  }
  for (int i = 0; i < n; i++) {
    int k = i + 1 < n ? i : n - 2; /* the direction to the next point; the last point: the last segment's */
    double direction = atan2(py[k + 1] - py[k], px[k + 1] - px[k]);
    double deviation = angle_difference(pyaw[i], direction);
    if (deviation > MAX_YAW_DEVIATION) {
      snprintf(err, err_len, "%s: line %d: yaw %.4f rad is %.3f rad from the direction of the points (%.4f rad; "
               "at most %g rad)", where, line_of[i], pyaw[i], deviation, direction, MAX_YAW_DEVIATION);
      return -1;
    }
  }
  for (int i = 0; i + 2 < n; i++) {
    double d0 = atan2(py[i + 1] - py[i], px[i + 1] - px[i]), d1 = atan2(py[i + 2] - py[i + 1], px[i + 2] - px[i + 1]);
    double turn = angle_difference(d1, d0);
    if (turn > MAX_SEGMENT_TURN) {
      snprintf(err, err_len, "%s: line %d: the path turns by %.3f rad at this point (at most %g rad; no doubling "
               "back)", where, line_of[i + 1], turn, MAX_SEGMENT_TURN);
      return -1;
    }
  }
  return 0;
}

/* ReferencePath.from_arrays: yaw wrapped then unwrapped (numpy.unwrap), s the chord sum. */
static void path_arrays(const points_t *p, int n) {
  double *px = p->x, *py = p->y, *pyaw = p->yaw, *ps = p->s;
  double correction = 0.0, previous = wrap_angle(pyaw[0]);
  ps[0] = 0.0;
  pyaw[0] = previous;
  for (int i = 1; i < n; i++) {
    ps[i] = ps[i - 1] + hypot(px[i] - px[i - 1], py[i] - py[i - 1]);
    double wrapped = wrap_angle(pyaw[i]);
    double dd = wrapped - previous, ddmod = py_mod(dd + PI, TWO_PI) - PI;
    if (ddmod == -PI && dd > 0.0) ddmod = PI;
    if (fabs(dd) >= PI) correction += ddmod - dd;
    previous = wrapped;
    pyaw[i] = wrapped + correction;
  }
}

/* Read, check and convert one file into the free end of the pool; its point count in *n. */
static int read_path_file(ecu_path_pool_t *pool, const char *file, int *n_out, char *err, size_t err_len) {
  static char line[LINE_BYTES]; /* start-up only: one file is read at a time */
  int got;
  int capacity = ECU_MAX_PATH_POINTS - pool->used;
  const points_t free_end = {pool->x + pool->used, pool->y + pool->used, pool->yaw + pool->used,
                             pool->s + pool->used, pool->lines + pool->used};
  double *px = free_end.x, *py = free_end.y, *pyaw = free_end.yaw;
  int *line_of = free_end.line;
  FILE *stream = fopen(file, "r");
  int n = 0, line_number = 0, header_seen = 0, status = 0;
  if (!stream) {
    snprintf(err, err_len, "%s: path file not found", file);
    return -1;
  }
  ecu_lines_t lines = {.name = file, .stream = stream, .max_bytes = ECU_PATH_FILE_MAX};
  while (status == 0 && (got = ecu_read_line(&lines, line, err, err_len)) != 0) {
    char *cells[3], *cursor = line, joined[LINE_BYTES];
    int count = 1, blank = 1;
    if (got < 0) { /* a NUL byte, a line or a file too long (the Python ECU's verdict) */
      status = -1;
      break;
    }
    line_number++;
    for (const char *c = line; *c; c++) count += *c == ',';
    for (const char *c = line; *c; c++) blank = blank && (isspace((unsigned char)*c) || *c == ',');
    if (blank) continue;
    for (int j = 0; j < 3 && j < count; j++) {
      cells[j] = cursor;
      char *comma = strchr(cursor, ',');
      if (comma) {
        *comma = '\0';
        cursor = comma + 1;
      }
    }
    if (!header_seen) {
      header_seen = 1;
      if (count != 3 || strcmp(trim(cells[0]), "x") || strcmp(trim(cells[1]), "y") || strcmp(trim(cells[2]), "yaw")) {
        size_t used = 0;
        joined[0] = '\0';
        for (int j = 0; j < 3 && j < count && used < sizeof joined; j++)
          used += (size_t)snprintf(joined + used, sizeof joined - used, j ? ",%s" : "%s", trim(cells[j]));
        snprintf(err, err_len, "%s: line %d: header must be 'x,y,yaw', got '%s%s'", file, line_number, joined,
                 count > 3 ? ",..." : "");
        status = -1;
      }
      continue;
    }
    if (n == ECU_MAX_PATH_POINTS) {
      snprintf(err, err_len, "%s: line %d: more than 100,000 points (the contract's limit)", file, line_number);
      status = -1;
      break;
    }
    if (n == capacity) {
      snprintf(err, err_len, "%s: line %d: the paths together exceed the ECU's %d points", file, line_number,
               ECU_MAX_PATH_POINTS);
      status = -1;
      break;
    }
    if (count != 3) {
      snprintf(err, err_len, "%s: line %d has %d columns, expected 3", file, line_number, count);
      status = -1;
      break;
    }
    double *targets[3] = {&px[n], &py[n], &pyaw[n]};
    for (int j = 0; j < 3 && status == 0; j++) {
      int ok;
      char original[256];
      snprintf(original, sizeof original, "%s", cells[j]);
      *targets[j] = parse_number(cells[j], &ok);
      if (!ok) {
        snprintf(err, err_len, "%s: line %d column %s: not a number: '%s'", file, line_number, HEADER[j], original);
        status = -1;
      }
    }
    line_of[n++] = line_number;
  }
  fclose(stream);
  if (status != 0) return -1;
  if (!header_seen) {
    snprintf(err, err_len, "%s: empty file (expected header 'x,y,yaw')", file);
    return -1;
  }
  if (check_points(&free_end, file, n, err, err_len) != 0) return -1;
  path_arrays(&free_end, n);
  *n_out = n;
  return 0;
}

void ecu_paths_reset(ecu_path_pool_t *pool) {
  pool->used = 0;
  pool->n_slices = 0;
}

int ecu_paths_add(ecu_path_pool_t *pool, int path_id, const char *file, char *err, size_t err_len) {
  int n = 0;
  if (pool->n_slices == ECU_MAX_POOL_PATHS) {
    snprintf(err, err_len, "%s: more than %d paths", file, ECU_MAX_POOL_PATHS);
    return -1;
  }
  if (read_path_file(pool, file, &n, err, err_len) != 0) return -1;
  pool->slices[pool->n_slices].id = path_id;
  pool->slices[pool->n_slices].first = pool->used;
  pool->slices[pool->n_slices++].n = n;
  pool->used += n;
  return 0;
}

int ecu_paths_has(const ecu_path_pool_t *pool, int path_id) {
  for (int k = 0; k < pool->n_slices; k++)
    if (pool->slices[k].id == path_id) return 1;
  return 0;
}

int ecu_paths_find(const ecu_path_pool_t *pool, int path_id, ecu_path_view_t *view) {
  for (int k = pool->n_slices - 1; k >= 0; k--) {
    if (pool->slices[k].id == path_id) {
      int first = pool->slices[k].first;
      view->x = pool->x + first;
      view->y = pool->y + first;
      view->yaw = pool->yaw + first;
      view->s = pool->s + first;
      view->n = pool->slices[k].n;
      return 0;
    }
  }
  return -1;
}
