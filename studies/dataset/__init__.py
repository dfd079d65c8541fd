"""Auto-labelled datasets from the simulation (`rmmdet dataset generate`)."""
