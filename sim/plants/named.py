"""The named plants: ``make_plant(NAME, vehicle)`` for every name of :data:`PLANTS` (see :mod:`sim.plants.plant`)."""

from __future__ import annotations

import dataclasses

from ..errors import SimInputError
from ..params import NOMINAL, QuadParams
from .plant import Plant, SimPlant, WindFn
from ..vehicles.vehicle import load_vehicle

#: Plant names, the default first. ``drone-models[:PHYSICS]`` are the Crazyflie models identified from real flights
#: (:mod:`sim.plants.drone_models_plant`; the level ``ctatt`` only); ``crazyflow`` a Crazyflie simulated with its
#: Mellinger onboard loops (:mod:`sim.plants.crazyflow_plant`; ``ctbr`` and ``ctatt``).
PLANTS = ("sim", "rotorpy", "rotorpy-ideal", "drone-models", "drone-models:so_rpy", "drone-models:so_rpy_rotor",
          "crazyflow")
#: Plants whose equations this project knows (they have an oracle): our simulator's nominal set-up, and RotorPy
#: without motor lag and aerodynamics (the same rigid body, no drag). RotorPy's aerodynamics have no such form here.
KNOWN_EQUATIONS = ("sim", "rotorpy-ideal")


def rotorpy_available() -> bool:
    """True when RotorPy (the optional external plant) can be imported."""
    import importlib.util

    return importlib.util.find_spec("rotorpy") is not None


def known_equations(name: str, params: QuadParams) -> QuadParams | None:
    """The parameters of the rigid-body equations plant ``name`` integrates for a vehicle of ``params``, or None.

    ``sim``: ``params`` (its nominal set-up); ``rotorpy-ideal``: ``params`` without drag; ``rotorpy``: None (its
    motor lag and aerodynamics are not in the nominal equations).
    """
    if name not in PLANTS:
        raise SimInputError(f"plant must be one of {', '.join(PLANTS)}; found {name!r}")
    if name not in KNOWN_EQUATIONS:
        return None
    return dataclasses.replace(params, c_d=0.0) if name == "rotorpy-ideal" else params


def make_plant(name: str = "sim", vehicle=None, *, high_fidelity: bool = False, payload_kg: float = 0.0,
               wind: WindFn | None = None, level: str = "wrench") -> Plant:
    """The plant called ``name`` (one of :data:`PLANTS`) flying ``vehicle`` (a :class:`Vehicle`, name or file).

    ``high_fidelity`` switches on the vehicle's motor lag, rotor drag and gyroscopic torque in the reference
    simulator (the ``+highfi`` scenarios); RotorPy's plants have their own set-ups and refuse it.

    ``level`` (:mod:`sim.levels`): the command the plant takes. At ``ctbr`` and ``ctatt`` the reference simulator
    flies it through the vehicle's inner loop (:class:`sim.plants.inner_loop.InnerLoopPlant`, the vehicle file's
    ``[inner_loop]``), RotorPy through its own onboard controllers with that table's rate and gains
    (:class:`sim.plants.rotorpy_plant.RotorPyPlant`); a vehicle without one is refused. The drone-models plants
    (:class:`sim.plants.drone_models_plant.DroneModelsPlant`) take ``ctatt`` only; ``crazyflow``
    (:class:`sim.plants.crazyflow_plant.CrazyflowPlant`) ``ctbr`` and ``ctatt``.
    """
    from ..levels import DEFAULT_LEVEL, check_level

    vehicle = load_vehicle(vehicle)
    check_level(level)
    if level != DEFAULT_LEVEL and name == "sim":
        from .inner_loop import InnerLoopPlant

        loop = vehicle.inner_loop_at(level)
        base = make_plant(name, vehicle, high_fidelity=high_fidelity, payload_kg=payload_kg, wind=wind)
        return InnerLoopPlant(base, loop, level)
    if name == "sim":
        return SimPlant(vehicle, vehicle.fidelity if high_fidelity else NOMINAL, payload_kg=payload_kg, wind=wind)
    if name in ("rotorpy", "rotorpy-ideal"):
        if high_fidelity:
            raise SimInputError(f"high fidelity is a set-up of the reference simulator (plant 'sim'); plant {name!r} "
                                f"has its own (use --plant rotorpy for RotorPy's motor lag and aerodynamics)")
        from .rotorpy_plant import RotorPyPlant
        full = name == "rotorpy"
        return RotorPyPlant(vehicle, motor_lag=full, aero=full, payload_kg=payload_kg, wind=wind, level=level)
    if name in PLANTS and name.startswith("drone-models"):
        if high_fidelity:
            raise SimInputError(f"high fidelity is a set-up of the reference simulator (plant 'sim'); plant {name!r} "
                                f"is drone-models' fitted model, with its own thrust lag and drag")
        from .drone_models_plant import DroneModelsPlant, parse_plant_name

        return DroneModelsPlant(vehicle, parse_plant_name(name), level, payload_kg=payload_kg, wind=wind)
    if name == "crazyflow":
        if high_fidelity:
            raise SimInputError("high fidelity is a set-up of the reference simulator (plant 'sim'); plant "
                                "'crazyflow' has its own rotor dynamics")
        from .crazyflow_plant import CrazyflowPlant

        return CrazyflowPlant(vehicle, level, payload_kg=payload_kg, wind=wind)
    raise SimInputError(f"plant must be one of {', '.join(PLANTS)}; found {name!r}")
