# Issue 6, part 4: the closed-loop double-lane-change study without CAN (paper Tables II/III,
# Figs 8/9; compute time per step: make bench). See docs/study.md.
.PHONY: tables dlc-path

## paper Tables II/III and Figs 8/9 without CAN -> results/table2_*, table3_*
tables: setup
	$(PY) -m studies.paper_tables --out results
	$(PROVENANCE_STAMP) $(addprefix results/,table2_high_mu.md table3_low_mu.md fig8_high_mu.png fig9_low_mu.png \
		study_checks.md study_metrics.json) --command "make tables" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) --modules studies.paper_tables

# Issue 35 item 6: the same tables with every MPC's weights unscheduled (the low-speed set
# equal to the other, the weighting make tune's steps 1-3 chose for every speed), beside
# the scheduled ones of make tables (docs/tuning.md, "With and without the schedule").
.PHONY: tables-unscheduled
## Tables II/III with the MPCs' weights unscheduled (one weighting at every speed) -> results/unscheduled/
tables-unscheduled: setup
	@mkdir -p build results/unscheduled
	$(PY) -m studies.unscheduled_tuning --out build/tuning_unscheduled.toml --replace
	$(PY) -m studies.paper_tables --tuning build/tuning_unscheduled.toml --out results/unscheduled --no-progress
	rm -rf results/unscheduled/traces
	$(PROVENANCE_STAMP) $(addprefix results/unscheduled/,table2_high_mu.md table3_low_mu.md fig8_high_mu.png \
		fig9_low_mu.png study_checks.md study_metrics.json) --command "make tables-unscheduled" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) --modules studies.paper_tables studies.unscheduled_tuning

# Regenerates hil/paths/dlc.csv from the architecture's double-lane-change formula.
## regenerate hil/paths/dlc.csv from the double-lane-change formula
dlc-path: setup
	$(PY) -m hil.path_files
