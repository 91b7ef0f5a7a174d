/*
 * Revision 3 release of the control task by the plant's samples (firmware_sim/clock.py
 * SampleRelease; docs/can-contract.md, "Revision 3"), on integer ns of either time base.
 *
 * Unanchored (from the start, after ecu_release_reset), the node releases the task on its
 * 25 ms clock as in revision 2 and reports each release with ecu_release_note. A good
 * sample set anchors the grid of control instants N_k = anchor + k * 25 ms there: the
 * first one, and the first after none for more than 100 ms (when the task ran less than
 * 15 ms before it, that release stands for the instant and the grid anchors within 2.5 ms
 * of it, in phase with the samples, for a paced plant, sample_period_ns 25 ms, at the
 * sample). A paced plant's grid follows each
 * of its samples: one outside the pending instant's window anchors it again, one that
 * releases the task moves the instant to its arrival.
 * Anchored, instant N is released
 * by the first good sample set arriving in [N - 2.5 ms, N + 7.5 ms), else by the period
 * watchdog at N + 7.5 ms; one release per instant; two releases at least 15 ms apart.
 */
#ifndef ECU_RELEASE_H
#define ECU_RELEASE_H

#include <stdint.h>

#include "ecu_contract.h"
#include "ecu_types.h"

typedef struct {
  int anchored;
  int64_t instant_ns;   /* the pending control instant N (anchored) */
  int instant_released; /* N has had its release */
  ecu_when_t last_release, last_sample;
  int64_t sample_period_ns; /* the plant's (10 or 25 ms); ecu_release_reset keeps it */
} ecu_release_t;

/* Unanchored, nothing released (start-up, handshake, jump of virtual time). */
void ecu_release_reset(ecu_release_t *release);

/* A release of the node's own clock (unanchored). */
void ecu_release_note(ecu_release_t *release, int64_t now_ns);

/* Close the windows that ended by now_ns: 1 when the watchdog releases the task now;
 * *skipped: older unreleased instants skipped (a late loop). */
int ecu_release_on_time(ecu_release_t *release, int64_t now_ns, int *skipped);

/* A good plant sample set arrived at arrival_ns (ecu_release_on_time first): 1 when it
 * releases the task now. */
int ecu_release_on_sample(ecu_release_t *release, int64_t arrival_ns);

/* The rule fed a script of events, as the node feeds it (tests/test_release_rule_c.py gives
 * the Python rule the same scripts; the node itself never calls this). Event i at
 * times_ns[i] is kinds[i]: ECU_RELEASE_TIME, time passing (the watchdog, when anchored);
 * ECU_RELEASE_SAMPLE, a good plant sample set (the watchdog first, when anchored, then the
 * sample's own release); ECU_RELEASE_CLOCK, a release of the node's own 25 ms clock
 * (unanchored). Out, per event: released[i] bit 0 the watchdog released the task, bit 1
 * the sample did; skipped[i] the instants skipped; instants_ns[i] the pending instant
 * after it (0 unanchored). sample_period_ns: the plant's (10 or 25 ms). Returns 0, or -1
 * for n < 0, a null array or an unknown kind (outputs then undefined from that event). */
enum { ECU_RELEASE_TIME = 0, ECU_RELEASE_SAMPLE = 1, ECU_RELEASE_CLOCK = 2 };
ECU_API int ecu_release_script(int64_t sample_period_ns, const int32_t *kinds, const int64_t *times_ns, int32_t n,
                               int32_t *released, int32_t *skipped, int64_t *instants_ns);

#endif
