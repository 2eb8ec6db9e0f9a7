"""The Rodas tableaus of :mod:`physmend.simulate.rodas`: :class:`RodasTableau` and :data:`TABLEAUS`.

Tableaus (``TABLEAUS``), transcribed from OrdinaryDiffEq.jl
(``lib/OrdinaryDiffEqRosenbrock/src/rosenbrock_tableaus.jl``):

- ``rodas3``: A. Sandu et al., Atmos. Environ. 31 (1997) 3459, RODAS3: four stages, order
  3(2). Its second stage reuses ``f(t, u)``, so a step costs what an ode23s step costs (a
  Jacobian, ``df/dt`` and two more right-hand sides).
- ``rodas4``: E. Hairer, G. Wanner, *Solving Ordinary Differential Equations II* (2nd ed.,
  Springer 1996), section IV.7, their Fortran code RODAS: six stages, order 4(3). Loses order
  where stiff states follow time-dependent inputs with steps far longer than their time
  constants (the Prothero-Robinson situation: fast thermal nodes driven by inputs).
- ``rodas4p`` (G. Steinebach 1995, RODASP) and ``rodas4p2`` (G. Steinebach 2020): Rodas4's
  structure with coefficients that keep order 4 there; ``rodas4p2`` has the better dense output.
"""

from __future__ import annotations

from dataclasses import dataclass

from physmend.simulate.errors import SimulationError


@dataclass(frozen=True)
class RodasTableau:
    """Coefficients of a stiffly accurate Rosenbrock method in transformed form (``s`` stages).

    ``a[i]``, ``C[i]``: stage ``i + 1``'s coefficients on stages ``1 .. i`` (``a[0] = C[0] = ()``);
    ``c``: stage times as fractions of the step; ``d``: weights of ``h df/dt`` per stage;
    ``H``: two rows on the first stages' ``k`` for the dense output
    ``u(s) = (1 - s) u0 + s u1 + s (1 - s) (H_1 k + s H_2 k)``, ``s`` in [0, 1] (``()``: linear).
    The new solution is the last stage's argument plus its ``k`` (stiffly accurate). A stage
    with the time and ``a`` row of an earlier one reuses that stage's right-hand side.
    """

    name: str
    gamma: float
    a: tuple[tuple[float, ...], ...]
    C: tuple[tuple[float, ...], ...]
    c: tuple[float, ...]
    d: tuple[float, ...]
    H: tuple[tuple[float, ...], ...]
    order: int = 4  # of the method; the embedded (error-estimating) solution has order - 1


_A5 = (1.221224509226641, 6.019134481288629, 12.53708332932087, -0.6878860361058950)

RODAS4 = RodasTableau(
    name="rodas4",
    gamma=0.25,
    a=(
        (),
        (1.544,),
        (0.9466785280815826, 0.2557011698983284),
        (3.314825187068521, 2.896124015972201, 0.9986419139977817),
        _A5,
        (*_A5, 1.0),
    ),
    C=(
        (),
        (-5.6688,),
        (-2.430093356833875, -0.2063599157091915),
        (-0.1073529058151375, -9.594562251023355, -20.47028614809616),
        (7.496443313967647, -10.24680431464352, -33.99990352819905, 11.70890893206160),
        (8.083246795921522, -7.981132988064893, -31.52159432874371, 16.31930543123136, -6.058818238834054),
    ),
    c=(0.0, 0.386, 0.21, 0.63, 1.0, 1.0),
    d=(0.25, -0.1043, 0.1035, -0.0362, 0.0, 0.0),
    H=(
        (10.12623508344586, -7.487995877610167, -34.80091861555747, -7.992771707568823, 1.025137723295662),
        (-0.6762803392801253, 6.087714651680015, 16.43084320892478, 24.76722511418386, -6.594389125716872),
    ),
)


_A5P = (-7.170454962423024, -4.741636671481785, -16.31002631330971, -1.062004044111401)

#: Steinebach's RODASP (1995): Rodas4's structure, order 4 also on the Prothero-Robinson problem.
RODAS4P = RodasTableau(
    name="rodas4p",
    gamma=0.25,
    a=(
        (),
        (3.0,),
        (1.831036793486759, 0.4955183967433795),
        (2.304376582692669, -0.05249275245743001, -1.176798761832782),
        _A5P,
        (*_A5P, 1.0),
    ),
    C=(
        (),
        (-12.0,),
        (-8.791795173947035, -2.207865586973518),
        (10.81793056857153, 6.780270611428266, 19.53485944642410),
        (34.19095006749676, 15.49671153725963, 54.74760875964130, 14.16005392148534),
        (34.62605830930532, 15.30084976114473, 56.99955578662667, 18.40807009793095, -5.714285714285717),
    ),
    c=(0.0, 0.75, 0.21, 0.63, 1.0, 1.0),
    d=(0.25, -0.5, -0.023504, -0.0362, 0.0, 0.0),
    H=(
        (25.09876703708589, 11.62013104361867, 28.49148307714626, -5.664021568594133, 0.0),
        (1.638054557396973, -0.7373619806678748, 8.477918219238990, 15.99253148779520, -1.882352941176471),
    ),
)

_A5P2 = (7.089566927282776, 4.573591406461604, -8.423496976860259, -0.959280113459775)

#: Steinebach's improved RODASP (2020): order 4 on Prothero-Robinson, better dense output,
#: order 2 as a W-method (inexact Jacobian). ``H`` as in the current OrdinaryDiffEq.jl
#: (``lib/OrdinaryDiffEqRosenbrock``); older releases had three sign errors there.
RODAS4P2 = RodasTableau(
    name="rodas4p2",
    gamma=0.25,
    a=(
        (),
        (3.0,),
        (0.906377755268814, -0.189707390391685),
        (3.758617027739064, 1.161741776019525, -0.849258085312803),
        _A5P2,
        (*_A5P2, 1.0),
    ),
    C=(
        (),
        (-12.0,),
        (-6.354581592719008, 0.338972550544623),
        (-8.575016317114033, -7.606483992117508, 12.224997650124820),
        (-5.888975457523102, -8.157396617841821, 24.805546872612922, 12.790401512796979),
        (-4.408651676063871, -6.692003137674639, 24.625568527593117, 16.627521966636085, -5.714285714285718),
    ),
    c=(0.0, 0.75, 0.321448134013046, 0.519745732277726, 1.0, 1.0),
    d=(0.25, -0.5, -0.189532918363016, 0.085612108792769, 0.0, 0.0),
    H=(
        (-5.323528268423303, -10.042123754867493, 17.175254928256965, -5.079931171878093, -0.016185991706112),
        (6.984505741529879, 6.914061169603662, -0.849178943070653, 18.104410789349338, -3.516963011559032),
    ),
)

#: Sandu et al. (1997), RODAS3: four stages, order 3(2); the second stage reuses f(t, u).
RODAS3 = RodasTableau(
    name="rodas3",
    gamma=0.5,
    a=((), (0.0,), (2.0, 0.0), (2.0, 0.0, 1.0)),
    C=((), (4.0,), (1.0, -1.0), (1.0, -1.0, -8.0 / 3.0)),
    c=(0.0, 0.0, 1.0, 1.0),
    d=(0.5, 1.5, 0.0, 0.0),
    H=(),
    order=3,
)

#: The tableaus by name (``odeint_rodas(..., tableau=NAME)``).
TABLEAUS = {tab.name: tab for tab in (RODAS3, RODAS4, RODAS4P, RODAS4P2)}


def tableau_named(name: str) -> RodasTableau:
    """The tableau ``name`` of :data:`TABLEAUS`; SimulationError naming the choices otherwise."""
    if name not in TABLEAUS:
        raise SimulationError(f"tableau must be one of {sorted(TABLEAUS)}, but got {name!r}")
    return TABLEAUS[name]
