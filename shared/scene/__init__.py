"""Scene: the one source of truth for the table layout, road network, agents and sensors."""
