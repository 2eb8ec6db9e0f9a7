"""The engineer's model of a refrigerated two-zone cargo box (after the seed paper).

An insulated box of inner width ``box.width`` and height ``box.height`` is split by a bulkhead
into zone 1 (front, length ``zone1.length``) and zone 2 (rear, length ``zone2.length``). Each
zone holds

* a well-mixed air volume ``zoneN.air`` (state ``zoneN.air.T``, degC, the measured output);
* its envelope (roof, floor and both side walls, area ``2 (W + H) L``), a foam wall discretised
  into :data:`ENVELOPE_LAYERS` layers, with inside and outside convection films;
* its end wall (``zone1.front_wall``; ``zone2.rear_doors``), :data:`END_WALL_LAYERS` layers;
* a lumped cargo mass ``zoneN.cargo`` (capacity and surface proportional to the zone length)
  that exchanges heat with the air by convection;
* an evaporator coil ``zoneN.coil`` (thermal mass, coil-to-air conductance ``hA``) from which
  the refrigeration unit removes the recorded heat flow ``zoneN.cooling.Q`` (W, >= 0).

The bulkhead (:data:`BULKHEAD_LAYERS` layers) conducts heat between the two air volumes, with
a convection film on each face. Outside films connect to the ambient temperature input
``ambient.T``. Every state starts at ``box.T_initial`` (the box is soaked at one temperature).

After structural simplification the model has 28 differential states:
3 per zone (air, cargo, coil) + 2 x (5 envelope + 4 end-wall layers) + 4 bulkhead layers.

Everything geometry-dependent (volumes, areas, capacities) is a sympy expression of the zone
lengths, so one model serves every configuration; the lengths are set per experiment.
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from physmend.modeling import Connector, Model
from physmend.modeling import thermal as th

T_UNIT = "degC"
ENVELOPE_LAYERS = 5
END_WALL_LAYERS = 4
BULKHEAD_LAYERS = 4
N_STATES = 3 * 2 + 2 * (ENVELOPE_LAYERS + END_WALL_LAYERS) + BULKHEAD_LAYERS  # = 28

INPUTS = ("ambient.T", "zone1.cooling.Q", "zone2.cooling.Q")
OUTPUTS = ("zone1.air.T", "zone2.air.T")
ZONES = ("zone1", "zone2")
END_WALLS = {"zone1": "front_wall", "zone2": "rear_doors"}


@dataclass(frozen=True)
class BoxParameters:
    """Symbols of the box-wide parameters (shared by both zones)."""

    width: sp.Symbol
    height: sp.Symbol
    T_initial: sp.Symbol
    h_inside: sp.Symbol
    h_outside: sp.Symbol
    wall_thickness: sp.Symbol
    wall_k: sp.Symbol
    wall_rho: sp.Symbol
    wall_cp: sp.Symbol
    bulkhead_thickness: sp.Symbol
    bulkhead_k: sp.Symbol
    bulkhead_rho: sp.Symbol
    bulkhead_cp: sp.Symbol
    cargo_mass_per_length: sp.Symbol
    cargo_cp: sp.Symbol
    cargo_area_per_length: sp.Symbol


def _box_parameters(m: Model) -> BoxParameters:
    """Declare the box-wide parameters with realistic values (SI units, temperatures in degC)."""
    p = m.parameter
    return BoxParameters(
        width=p("box.width", 2.5, unit="m", description="inner width of the box"),
        height=p("box.height", 2.5, unit="m", description="inner height of the box"),
        T_initial=p(
            "box.T_initial", 28.0, unit=T_UNIT,
            description="start temperature of every state (box soaked at one temperature)",
        ),
        h_inside=p(
            "box.h_inside", 6.0, unit="W/(m2.K)", uncertain=True, bounds=(2.0, 15.0),
            description="inside convection coefficient (air to walls and cargo, fans running)",
        ),
        h_outside=p("box.h_outside", 20.0, unit="W/(m2.K)", description="outside convection coefficient"),
        wall_thickness=p("wall.thickness", 0.09, unit="m", description="polyurethane foam thickness of box walls"),
        wall_k=p("wall.conductivity", 0.025, unit="W/(m.K)", description="thermal conductivity of wall foam"),
        wall_rho=p("wall.density", 40.0, unit="kg/m3", description="density of wall foam"),
        wall_cp=p("wall.cp", 1400.0, unit="J/(kg.K)", description="specific heat of wall foam"),
        bulkhead_thickness=p("bulkhead.thickness", 0.05, unit="m", description="foam thickness of the bulkhead"),
        bulkhead_k=p("bulkhead.conductivity", 0.025, unit="W/(m.K)", description="conductivity of bulkhead foam"),
        bulkhead_rho=p("bulkhead.density", 40.0, unit="kg/m3", description="density of bulkhead foam"),
        bulkhead_cp=p("bulkhead.cp", 1400.0, unit="J/(kg.K)", description="specific heat of bulkhead foam"),
        cargo_mass_per_length=p(
            "cargo.mass_per_length", 120.0, unit="kg/m",
            description="cargo (pallets, packaging, product) mass per metre of zone length",
        ),
        cargo_cp=p(
            "cargo.cp", 1800.0, unit="J/(kg.K)", uncertain=True, bounds=(800.0, 3600.0),
            description="specific heat of the cargo",
        ),
        cargo_area_per_length=p(
            "cargo.area_per_length", 6.0, unit="m2/m",
            description="cargo surface exposed to the air per metre of zone length",
        ),
    )


def _insulated_wall(
    m: Model, name: str, *, area: sp.Expr, inside: Connector, outside: Connector, layers: int,
    thickness: sp.Expr, k: sp.Expr, rho: sp.Expr, cp: sp.Expr, h_in: sp.Expr, h_out: sp.Expr,
    T_start: sp.Expr,
) -> th.Component:
    """A layered wall of ``area`` (m2) with convection films ``name.film_in`` / ``name.film_out``.

    ``inside`` and ``outside`` are the heat ports the films attach to; face ``a`` is inside.
    """
    wall = th.layered_wall(
        m, name, area=area, thickness=thickness, conductivity=k, density=rho, cp=cp,
        n_layers=layers, T_start=T_start, T_unit=T_UNIT,
    )
    film_in = th.convection(m, f"{name}.film_in", h_in, area, T_unit=T_UNIT)
    film_out = th.convection(m, f"{name}.film_out", h_out, area, T_unit=T_UNIT)
    m.connect(inside, film_in.a)
    m.connect(film_in.b, wall.a)
    m.connect(wall.b, film_out.a)
    m.connect(film_out.b, outside)
    return wall


def _zone(m: Model, zone: str, box: BoxParameters, ambient: th.Component) -> th.Component:
    """Add one zone (air, envelope, end wall, cargo, evaporator coil); return its air volume."""
    length = m.parameter(
        f"{zone}.length", 6.0, unit="m", description=f"length of {zone} (configuration parameter)"
    )
    coil_C = m.parameter(
        f"{zone}.coil.capacity", 25000.0, unit="J/K",
        description=f"thermal mass of the {zone} evaporator coil (fins, tubes, refrigerant)",
    )
    coil_hA = m.parameter(
        f"{zone}.coil.hA", 600.0, unit="W/K", description=f"coil-to-air conductance of the {zone} evaporator (fan on)"
    )
    cooling_Q = m.input(
        f"{zone}.cooling.Q", unit="W", description=f"heat removed from the {zone} evaporator coil (>= 0)"
    )
    T0 = box.T_initial
    air = th.air_volume(m, f"{zone}.air", box.width * box.height * length, T_start=T0, T_unit=T_UNIT)

    wall_kw = dict(
        thickness=box.wall_thickness, k=box.wall_k, rho=box.wall_rho, cp=box.wall_cp,
        h_in=box.h_inside, h_out=box.h_outside, T_start=T0,
    )
    _insulated_wall(
        m, f"{zone}.envelope", area=2 * (box.width + box.height) * length,
        inside=air.port, outside=ambient.port, layers=ENVELOPE_LAYERS, **wall_kw,
    )
    _insulated_wall(
        m, f"{zone}.{END_WALLS[zone]}", area=box.width * box.height,
        inside=air.port, outside=ambient.port, layers=END_WALL_LAYERS, **wall_kw,
    )

    cargo = th.heat_capacitor(
        m, f"{zone}.cargo", box.cargo_mass_per_length * length * box.cargo_cp, T_start=T0, T_unit=T_UNIT,
        description=f"temperature of the cargo in {zone}",
    )
    cargo_film = th.convection(m, f"{zone}.cargo_film", box.h_inside, box.cargo_area_per_length * length, T_unit=T_UNIT)
    m.connect(air.port, cargo_film.a)
    m.connect(cargo_film.b, cargo.port)

    coil = th.heat_capacitor(
        m, f"{zone}.coil", coil_C, T_start=T0, T_unit=T_UNIT, description=f"temperature of the {zone} evaporator coil"
    )
    coil_film = th.thermal_conductor(m, f"{zone}.coil_film", coil_hA, T_unit=T_UNIT)
    cooling = th.prescribed_heat_flow(m, f"{zone}.cooling", -cooling_Q, T_unit=T_UNIT)
    m.connect(air.port, coil_film.a)
    m.connect(coil_film.b, coil.port, cooling.port)

    m.output(f"{zone}.air.T", air.T, unit=T_UNIT, description=f"measured air temperature of {zone}")
    return air


def build_model() -> Model:
    """The engineer's two-zone cargo box model (28 states after simplification).

    Inputs: ``ambient.T`` (degC), ``zone1.cooling.Q`` and ``zone2.cooling.Q`` (W removed, >= 0).
    Outputs: ``zone1.air.T`` and ``zone2.air.T`` (degC). The configuration parameters
    ``zone1.length`` / ``zone2.length`` (m) and ``box.T_initial`` (degC) are set per experiment.
    """
    m = Model(
        "cargo_box",
        description="refrigerated two-zone cargo box: air, cargo, evaporator coils, layered walls, bulkhead",
    )
    box = _box_parameters(m)
    T_ambient = m.input("ambient.T", unit=T_UNIT, description="outside air temperature")
    ambient = th.prescribed_temperature(m, "ambient", T_ambient, T_unit=T_UNIT)
    air1 = _zone(m, "zone1", box, ambient)
    air2 = _zone(m, "zone2", box, ambient)
    _insulated_wall(
        m, "bulkhead", area=box.width * box.height, inside=air1.port, outside=air2.port,
        layers=BULKHEAD_LAYERS, thickness=box.bulkhead_thickness, k=box.bulkhead_k, rho=box.bulkhead_rho,
        cp=box.bulkhead_cp, h_in=box.h_inside, h_out=box.h_inside, T_start=box.T_initial,
    )
    return m
