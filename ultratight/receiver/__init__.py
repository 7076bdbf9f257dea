"""Processing: acquisition, correlators, tracking, PVT, the ultra-tight engine, scenarios, CLI."""
