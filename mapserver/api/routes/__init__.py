"""One router per resource: health, sessions (uploads), jobs, maps."""
