"""Pure geometry in float64: perspectives, the oblique cameras, the sun, point-to-surface distances."""
