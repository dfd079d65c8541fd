"""Each service's name: the `service` chunk of its presence and health keys
(`rmmdet/v1/{scope}/@alive/{service}/{instance}`). One home: the services announce themselves under
these, and the health verdict, the identities and whoever watches a presence read them from here."""

from __future__ import annotations

ROUTER = "router"
SIM = "sim"
SENSOR = "sensor"  # a sensor group of the sim, or of real devices (services/device)
EMULATOR = "emulator"  # a sensor group sending the devices' wire formats (make up SENSORS=wire)
MEC = "mec"
COORDINATOR = "coordinator"
RECORDER = "recorder"
VIEWER = "viewer"
WATCHDOG = "watchdog"
VEHICLE = "vehicle"
