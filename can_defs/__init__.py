"""can_defs package."""
