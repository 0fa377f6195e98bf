"""Bad-input corpus and reader fuzzing for MISS (generated from code, no patient data)."""
