"""Route requests from vehicles the coordinator holds nothing for, taken within a rate (issue 52 item 10;
shared/bus/admission.py): the unsharded coordinator checks before it plans, a shard before it asks the
others to release the vehicle."""

from __future__ import annotations

import time

from rmmdet.v1.common_pb2 import ErrorCode

from shared.bus.admission import NewcomerAdmission
from shared.bus.rpc import RpcRejected
from shared.traffic.config import CoordinatorSettings

UNAVAILABLE = ErrorCode.ERROR_CODE_UNAVAILABLE


def newcomer_admission(settings: CoordinatorSettings) -> NewcomerAdmission:
    return NewcomerAdmission(settings.service.new_vehicles_per_s, settings.service.new_vehicle_burst)


def admit_newcomer(admission: NewcomerAdmission, vehicle_id: str) -> None:
    """Serve a vehicle this coordinator holds nothing for only within the newcomers' rate (issue 52
    item 10); RpcRejected (`rejected/new_vehicle_rate`, UNAVAILABLE) beyond it."""
    if not admission.admit(time.monotonic()):
        raise RpcRejected(
            "new_vehicle_rate", UNAVAILABLE, f"{vehicle_id[:64]}: too many new vehicles; ask again later"
        )
