"""MEC (edge) service: one agent's detection, fusion and tracking."""
