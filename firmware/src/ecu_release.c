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

int ecu_release_on_sample(ecu_release_t *release, int64_t arrival_ns) {
  int restarted = !release->last_sample.set || arrival_ns - release->last_sample.ns > SAMPLE_LOST_MS * NS_PER_MS;
  release->last_sample.set = 1;
  release->last_sample.ns = arrival_ns;
  if (!release->anchored || restarted) {
    release->anchored = 1;
    release->instant_released = 1;
    if (!spaced(release, arrival_ns)) { /* the release just before is this instant's: the grid anchors there */
      release->instant_ns = release->last_release.ns;
      return 0;
    }
    release->instant_ns = arrival_ns;
    ecu_release_note(release, arrival_ns);
    return 1;
  }
  if (release->instant_released || arrival_ns < release->instant_ns - SAMPLE_WINDOW_EARLY_NS) return 0;
  if (!spaced(release, arrival_ns)) return 0;
  release->instant_released = 1;
  ecu_release_note(release, arrival_ns);
  return 1;
}
