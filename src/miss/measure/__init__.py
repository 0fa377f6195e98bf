"""The distance between two surfaces and a decimation's bound check, in millimetres."""
