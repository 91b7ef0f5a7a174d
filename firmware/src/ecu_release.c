/*
 * Revision 3 release of the control task (see ecu_release.h).
 */
#include "ecu_release.h"

static const int64_t period = CONTROL_PERIOD_MS * NS_PER_MS;

void ecu_release_reset(ecu_release_t *release) {
  release->anchored = 0;
  release->instant_ns = 0;
  release->instant_released = 0;
  release->last_release.set = release->last_sample.set = 0;
}

void ecu_release_note(ecu_release_t *release, int64_t now_ns) {
  release->last_release.set = 1;
  release->last_release.ns = now_ns;
}

int ecu_release_on_time(ecu_release_t *release, int64_t now_ns, int *skipped) {
  int missed = 0;
  *skipped = 0;
  if (!release->anchored) return 0;
  while (now_ns >= release->instant_ns + SAMPLE_WATCHDOG_NS) {
    missed += !release->instant_released;
    release->instant_ns += period;
    release->instant_released = 0;
  }
  if (!missed) return 0;
  ecu_release_note(release, now_ns);
  *skipped = missed - 1;
  return 1;
}

/* Whether a release at now_ns keeps the minimum spacing from the previous one. */
static int spaced(const ecu_release_t *release, int64_t now_ns) {
  return !release->last_release.set || now_ns - release->last_release.ns >= MIN_RELEASE_SPACING_NS;
}

/* A plant with one sample per control period (25 ms, slower than a window is wide): its
 * samples pace the task, and the grid follows each one. */
static int paced(const ecu_release_t *release) {
  return release->sample_period_ns > SAMPLE_WINDOW_EARLY_NS + SAMPLE_WATCHDOG_NS;
}

static int64_t gcd(int64_t a, int64_t b) {
  while (b != 0) {
    int64_t r = a % b;
    a = b;
    b = r;
  }
  return a;
}

/* ((offset_ns + g/2) mod g) - g/2 with the mod taken non-negative as Python's, g the phase
 * step gcd(period, sample period): offset_ns's signed phase against the samples' grid. */
static int64_t signed_phase(const ecu_release_t *release, int64_t offset_ns) {
  int64_t step = gcd(period, release->sample_period_ns);
  int64_t rest = (offset_ns + step / 2) % step;
  if (rest < 0) rest += step;
  return rest - step / 2;
}

/* The move of the pending instant for a 10 ms plant's sample that released it at arrival_ns:
 * its phase error e = ((arrival - N + g/2) mod g) - g/2 over PHASE_FOLLOW_DIVISOR, truncated
 * toward zero, so that the grid follows the samples' phase (a first sample apart from the
 * next ones' phase, a drifting clock) and jitter is averaged. 0 in lockstep. */
static int64_t phase_follow(const ecu_release_t *release, int64_t arrival_ns) {
  int64_t error = signed_phase(release, arrival_ns - release->instant_ns);
  int64_t move = (error >= 0 ? error : -error) / PHASE_FOLLOW_DIVISOR;
  return error >= 0 ? move : -move;
}

/* The instant nearest release_ns in phase with the samples arriving at arrival_ns + k x the
 * sample period, modulo the phase step g = gcd(period, sample period) (5 ms for a 10 ms
 * plant): release + ((arrival - release + g/2) mod g) - g/2, the mod taken non-negative as
 * Python's. The samples then sit 2.5 ms inside both edges of their windows. */
static int64_t in_phase(const ecu_release_t *release, int64_t release_ns, int64_t arrival_ns) {
  return release_ns + signed_phase(release, arrival_ns - release_ns);
}

/* Anchor the grid on the sample that arrived at arrival_ns: 1 when it runs the task. Not
 * when the task ran less than the minimum spacing before it: that release stands for the
 * instant, and the grid anchors within half a phase step of it, in phase with the samples
 * (a 10 ms plant: one of its samples is in every window), or, for a paced plant, at the
 * sample (its next sample comes at its instant). */
static int anchor(ecu_release_t *release, int64_t arrival_ns) {
  release->anchored = 1;
  release->instant_released = 1;
  if (!spaced(release, arrival_ns)) {
    release->instant_ns = paced(release) ? arrival_ns : in_phase(release, release->last_release.ns, arrival_ns);
    return 0;
  }
  release->instant_ns = arrival_ns;
  ecu_release_note(release, arrival_ns);
  return 1;
}

int ecu_release_on_sample(ecu_release_t *release, int64_t arrival_ns) {
  int restarted = !release->last_sample.set || arrival_ns - release->last_sample.ns > SAMPLE_LOST_MS * NS_PER_MS;
  release->last_sample.set = 1;
  release->last_sample.ns = arrival_ns;
  int off_window = arrival_ns < release->instant_ns - SAMPLE_WINDOW_EARLY_NS;
  /* A paced plant's sample outside the window (a late first sample, a plant whose phase
   * moved) anchors the grid too, or each later one would miss its window. */
  if (!release->anchored || restarted || (off_window && paced(release))) return anchor(release, arrival_ns);
  if (release->instant_released || off_window) return 0;
  if (!spaced(release, arrival_ns)) return 0;
  release->instant_released = 1;
  ecu_release_note(release, arrival_ns);
  if (paced(release))
    release->instant_ns = arrival_ns; /* the grid follows the plant's phase, drift included */
  else
    release->instant_ns += phase_follow(release, arrival_ns);
  return 1;
}

int ecu_release_script(int64_t sample_period_ns, const int32_t *kinds, const int64_t *times_ns, int32_t n,
                       int32_t *released, int32_t *skipped, int64_t *instants_ns) {
  if (n < 0 || sample_period_ns <= 0 || (n > 0 && (!kinds || !times_ns || !released || !skipped || !instants_ns)))
    return -1;
  ecu_release_t release;
  release.sample_period_ns = sample_period_ns;
  ecu_release_reset(&release);
  for (int32_t i = 0; i < n; i++) {
    int64_t t = times_ns[i];
    int missed = 0, flags = 0;
    switch (kinds[i]) {
    case ECU_RELEASE_TIME:
      flags = ecu_release_on_time(&release, t, &missed);
      break;
    case ECU_RELEASE_SAMPLE:
      if (release.anchored) flags = ecu_release_on_time(&release, t, &missed);
      flags |= ecu_release_on_sample(&release, t) << 1;
      break;
    case ECU_RELEASE_CLOCK:
      ecu_release_note(&release, t);
      break;
    default:
      return -1;
    }
    released[i] = flags;
    skipped[i] = missed;
    instants_ns[i] = release.anchored ? release.instant_ns : 0;
  }
  return 0;
}
