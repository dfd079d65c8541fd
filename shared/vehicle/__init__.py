"""A connected vehicle's side of the system: its plan client (the sim's vehicles and `rmmdet vehicle`)."""
