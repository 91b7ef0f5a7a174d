/*
 * The path search both trackers share (the control core's and the excitation's): a port
 * of numpy.searchsorted and controller.reference.PathTracker.update. Pure functions.
 */
#ifndef ECU_PATH_SEARCH_H
#define ECU_PATH_SEARCH_H

/* numpy.searchsorted(s, v, side) on s[0..n-1] (ascending): the first index i with
 * s[i] > v when right != 0 (side="right"), s[i] >= v when right == 0 (side="left"); n when
 * there is none, so v goes in before index i and s stays sorted. */
int ecu_search_sorted(const double *s, int n, double v, int right);

/* controller.reference.PathTracker.update (window 2 m behind, 6 m ahead) on a path of
 * n >= 2 points x, y, s (n,) (s increasing): the nearest foot point of (px, py) on the
 * segments around *progress, on all of them when !*has_progress. Sets *progress to the
 * foot point's arc length (m) and *has_progress to 1; returns the signed lateral error (m,
 * > 0 when the point is left of the path). */
double ecu_path_track(const double *x, const double *y, const double *s, int n, double px, double py,
                      double *progress, int *has_progress);

#endif
