# After a tuning stage writes controller/tuning.toml (make tune, the observer stages, make
# grip-envelope; docs/tuning.md), every study whose results take the tuning file as an input
# is stale. `make after-tuning` reruns them one after the other, each after the files it
# reads (make identify before make identify-lsq, make faults before make faults-c, make
# table1's seed models before make seed-spread), and make bench and make timing last, which
# measure the machine and want it idle. About 3 h on 2 cores (and 39 min more where
# build/table1/ lacks the seed models). tests/test_after_tuning.py checks the list against results/PROVENANCE.json: every
# stamped study with the tuning file among its inputs is in it, or is a tuning stage.
# AFTER_TUNING_FROM=TARGET starts at TARGET (to go on after a stop).
AFTER_TUNING_TARGETS := firmware tables tables-unscheduled run observer-variants delay-compensation \
	faults faults-c campaign-smoke campaign firmware-footprint pose-step observer-speed disturbances \
	robustness tradeoff grip-margin identify identify-lsq seed-spread-models seed-spread replay-report \
	vehicle-variants bench timing
AFTER_TUNING_FROM ?= firmware
.PHONY: after-tuning
## rerun every study the tuning file feeds, in order (~3 h; AFTER_TUNING_FROM=TARGET to go on)
after-tuning: setup
	@case " $(AFTER_TUNING_TARGETS) " in *" $(AFTER_TUNING_FROM) "*) ;; \
		*) echo "error: AFTER_TUNING_FROM=$(AFTER_TUNING_FROM) is not one of: $(AFTER_TUNING_TARGETS)" >&2; exit 2;; esac
	@started=; for target in $(AFTER_TUNING_TARGETS); do \
		[ "$$target" = "$(AFTER_TUNING_FROM)" ] && started=1; [ -n "$$started" ] || continue; \
		echo "== make $$target ($$(date -u +%H:%M) UTC)"; \
		$(MAKE) --no-print-directory $$target || exit 1; \
	done
