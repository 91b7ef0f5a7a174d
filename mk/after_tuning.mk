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

# $(call run_in_order,TARGETS,FROM,VARIABLE): make each of TARGETS in turn from FROM on (the
# value of VARIABLE, which names it in the error), stopping at the first that fails.
define run_in_order
	@case " $(1) " in *" $(2) "*) ;; \
		*) echo "error: $(3)=$(2) is not one of: $(1)" >&2; exit 2;; esac
	+@started=; for target in $(1); do \
		[ "$$target" = "$(2)" ] && started=1; [ -n "$$started" ] || continue; \
		echo "== make $$target ($$(date -u +%H:%M) UTC)"; \
		$(MAKE) --no-print-directory $$target || exit 1; \
	done
endef

.PHONY: after-tuning
## rerun every study the tuning file feeds, in order (~3 h; AFTER_TUNING_FROM=TARGET to go on)
after-tuning: setup
	$(call run_in_order,$(AFTER_TUNING_TARGETS),$(AFTER_TUNING_FROM),AFTER_TUNING_FROM)

# The whole tuning procedure and every study after it (docs/tuning.md, "The whole chain"):
# the stages in the order each takes the ones before it as given (the weights, the
# observers, their refinement, the heading target's side slip, the grip envelope), then
# the after-tuning list. About 6 h on 2 cores, so in several sittings: RETUNE_FROM=TARGET
# starts at TARGET (a stage or an after-tuning target) after a stop. It does not train: a
# new model is make train (and make dmdc) first.
RETUNE_STAGES := tune tune-observer tune-observer-refine tune-slip-target grip-envelope
RETUNE_TARGETS := $(RETUNE_STAGES) $(AFTER_TUNING_TARGETS)
RETUNE_FROM ?= tune
.PHONY: retune
## the whole tuning procedure, then every study after it (~6 h; RETUNE_FROM=TARGET to go on)
retune: setup
	$(call run_in_order,$(RETUNE_TARGETS),$(RETUNE_FROM),RETUNE_FROM)
