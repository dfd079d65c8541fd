"""Offline studies on the simulator: training datasets, the fusion evaluation, the flow experiment.

They drive the production cores (`shared.perception.core.MecCore`, `shared.traffic.core.CoordinatorCore`)
in lock step with the simulator (`sim.lockstep`), so their numbers are the services' numbers.
"""
