"""Cloud-side traffic functions, bus-free: lane matching, cross-agent merge, density and speed maps,
agent coverage, route planning and plan delivery bookkeeping. `services/coordinator` wires them to
the bus; `studies/experiments` runs them in lock-step with the simulation."""
