/*
 * The path search (see ecu_path_search.h): a binary search and the tracker's nearest foot
 * point within a window around the last progress.
 */
#include <math.h>

#include "ecu_path_search.h"

#define WINDOW_AHEAD 6.0  /* m: PathTracker's search window around the last progress */
#define WINDOW_BEHIND 2.0 /* m */

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
