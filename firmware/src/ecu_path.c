/*
 * Path files: the CSV reader and the contract's checks of controller/reference.py
 * (read_path_csv, check_path_file, ReferencePath.from_arrays), with the same messages.
 * The file is read line by line and refused at its 100,001st point. Differences from
 * Python's csv and float(): a quoted cell may not contain a comma, and numbers with
 * underscores ("1_000") or hexadecimal floats are refused. Also the path search both
 * trackers share (the control core's and the excitation's): ecu_search_sorted, ecu_path_track.
 */
#include <ctype.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ecu_excite.h"
#include "ecu_internal.h"
#include "ecu_lines.h"

#define PI 3.141592653589793
#define TWO_PI 6.283185307179586
#define MIN_FILE_POINT_SPACING 0.01 /* m */
#define MAX_POINT_SPACING 0.5       /* m */
#define MAX_YAW_DEVIATION 0.5       /* rad */
#define MAX_SEGMENT_TURN 0.5        /* rad */
#define POSITION_MIN (-8388.608)    /* m: the range of POS_X / POS_Y */
#define POSITION_MAX 8388.607
#define LINE_BYTES (ECU_LINE_MAX + 2)
#define WINDOW_AHEAD 6.0  /* m: PathTracker's search window around the last progress */
#define WINDOW_BEHIND 2.0 /* m */

static const char *const HEADER[3] = {"x", "y", "yaw"};
/* The pool of every loaded path, one after the other (ECU_MAX_PATH_POINTS in all). The
 * file being read goes to the free end; px .. line_of point there while it is checked. */
static double pool_x[ECU_MAX_PATH_POINTS], pool_y[ECU_MAX_PATH_POINTS], pool_yaw[ECU_MAX_PATH_POINTS];
static double pool_s[ECU_MAX_PATH_POINTS];
static int pool_lines[ECU_MAX_PATH_POINTS];
static int pool_used;
static double *px, *py, *pyaw, *ps;
static int *line_of;
#define MAX_POOL_PATHS 256
static struct { int id, first, n; } slices[MAX_POOL_PATHS];
static int n_slices;

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

static int check_points(const char *where, int n, char *err, size_t err_len) {
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
static void path_arrays(int n) {
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
static int read_path_file(const char *file, int *n_out, char *err, size_t err_len) {
  static char line[LINE_BYTES];
  int got;
  int capacity = ECU_MAX_PATH_POINTS - pool_used;
  px = pool_x + pool_used;
  py = pool_y + pool_used;
  pyaw = pool_yaw + pool_used;
  ps = pool_s + pool_used;
  line_of = pool_lines + pool_used;
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
  if (check_points(file, n, err, err_len) != 0) return -1;
  path_arrays(n);
  *n_out = n;
  return 0;
}

void ecu_path_pool_reset(void) {
  pool_used = 0;
  n_slices = 0;
}

int ecu_path_pool_add(int path_id, const char *file, char *err, size_t err_len) {
  int n = 0;
  if (n_slices == MAX_POOL_PATHS) {
    snprintf(err, err_len, "%s: more than %d paths", file, MAX_POOL_PATHS);
    return -1;
  }
  if (read_path_file(file, &n, err, err_len) != 0) return -1;
  slices[n_slices].id = path_id;
  slices[n_slices].first = pool_used;
  slices[n_slices++].n = n;
  pool_used += n;
  return 0;
}

int ecu_path_pool_has(int path_id) {
  for (int k = 0; k < n_slices; k++)
    if (slices[k].id == path_id) return 1;
  return 0;
}

int ecu_path_pool_select(int path_id, char *err, size_t err_len) {
  for (int k = n_slices - 1; k >= 0; k--) {
    if (slices[k].id == path_id) {
      int first = slices[k].first;
      return ecu_set_path(pool_x + first, pool_y + first, pool_yaw + first, pool_s + first, slices[k].n, err,
                          err_len);
    }
  }
  snprintf(err, err_len, "PATH_ID %d is not loaded", path_id);
  return -1;
}

int ecu_load_path_csv(const char *file, char *err, size_t err_len) {
  ecu_path_pool_reset();
  if (ecu_path_pool_add(0, file, err, err_len) != 0) return -1;
  return ecu_path_pool_select(0, err, err_len);
}

int ecu_search_sorted(const double *s, int n, double v, int right) {
  int lo = 0, hi = n;
  while (lo < hi) {
    int mid = (lo + hi) / 2;
    if (right ? s[mid] <= v : s[mid] < v) lo = mid + 1;
    else hi = mid;
  }
  return lo;
}

double ecu_path_track(const double *x, const double *y, const double *s, int n, double px, double py,
                      double *progress, int *has_progress) {
  int n_segments = n - 1, first = 0, last = n_segments;
  if (*has_progress) {
    first = ecu_search_sorted(s, n, *progress - WINDOW_BEHIND, 1) - 1;
    if (first < 0) first = 0;
    last = ecu_search_sorted(s, n, *progress + WINDOW_AHEAD, 0) + 1;
    if (last > n_segments) last = n_segments;
    if (last < first + 1) last = first + 1;
  }
  /* best_len_sq starts at 1: when no segment is nearer than infinity (coordinates so large
   * that d overflows) the progress is s[first] + 0 * 1, never 0 * inf. */
  double best = INFINITY, best_t = 0.0, best_ex = 0.0, best_ey = 0.0, best_len_sq = 1.0;
  int best_k = first;
  for (int k = first; k < last; k++) {
    double dx = x[k + 1] - x[k], dy = y[k + 1] - y[k];
    double length_sq = dx * dx + dy * dy;
    double t = ((px - x[k]) * dx + (py - y[k]) * dy) / length_sq;
    t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
    double ex = px - (x[k] + t * dx), ey = py - (y[k] + t * dy), d = ex * ex + ey * ey;
    if (d < best) {
      best = d;
      best_k = k;
      best_t = t;
      best_ex = ex;
      best_ey = ey;
      best_len_sq = length_sq;
    }
  }
  double length = sqrt(best_len_sq);
  *progress = s[best_k] + best_t * length;
  *has_progress = 1;
  /* cross product of the tangent with the offset: > 0 when the point is to the left */
  return ((x[best_k + 1] - x[best_k]) * best_ey - (y[best_k + 1] - y[best_k]) * best_ex) / length;
}

/* The excitation's e_Y: a tracker of its own on a pooled path, apart from the control core's. */
int ecu_path_pool_track(int path_id, double x, double y, double *progress, int *has_progress,
                        double *lateral_error) {
  int slice = -1;
  for (int k = n_slices - 1; k >= 0 && slice < 0; k--)
    if (slices[k].id == path_id) slice = k;
  if (slice < 0) return -1;
  int first = slices[slice].first;
  *lateral_error = ecu_path_track(pool_x + first, pool_y + first, pool_s + first, slices[slice].n, x, y, progress,
                                  has_progress);
  return 0;
}
