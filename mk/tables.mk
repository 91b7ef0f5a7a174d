# Issue 6, part 4: the closed-loop double-lane-change study without CAN (paper Tables II/III,
# Figs 8/9; compute time per step: make bench). See docs/study.md.
.PHONY: tables dlc-path

## paper Tables II/III and Figs 8/9 without CAN -> results/table2_*, table3_*
tables: setup
	$(PY) -m studies.paper_tables --out results
	$(PROVENANCE_STAMP) $(addprefix results/,table2_high_mu.md table3_low_mu.md fig8_high_mu.png fig9_low_mu.png \
		study_checks.md study_metrics.json) --command "make tables" \
		--inputs $(PROVENANCE_CLOSED_LOOP) $(PROVENANCE_DMDC) --modules studies.paper_tables
	@$(MAKE) --no-print-directory readme  # README.md includes these results

# Regenerates hil/paths/dlc.csv from the architecture's double-lane-change formula.
## regenerate hil/paths/dlc.csv from the double-lane-change formula
dlc-path: setup
	$(PY) -m hil.path_files
