"""Structural simplification: a semi-explicit DAE becomes an explicit ODE plus observed equations.

Steps (all exact, no approximation):

1. **Alias elimination** — equations of the form ``a = ±b`` or ``a = c`` (``c`` a state, input,
   parameter or constant) remove ``a`` (connection equations of acausal components).
2. **Matching and block ordering** — each remaining equation is matched to the unknown it
   determines (Hopcroft–Karp); strongly connected components give the order in which blocks
   are solved (BLT form).
3. **Symbolic solution** — each block is solved with sympy (scalar: linear or unique solution;
   larger blocks: linear systems). A block that cannot be solved this way is an error naming its
   equations.

The result expresses every state derivative, algebraic variable and output in states, inputs and
parameters only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import networkx as nx
import sympy as sp
from sympy.solvers.solveset import NonlinearError

from physmend.modeling.errors import ModelError
from physmend.modeling.parts import Declared, Equation, Variable, der_name
from physmend.modeling.recent import Recent


@dataclass
class SimplifiedModel:
    """Explicit ODE ``du/dt = f(u, x, p)`` with observed equations ``y = h(u, x, p)``.

    Attributes:
        name: model name.
        states, parameters, inputs: declared variables, in declaration order.
        rhs: state name -> expression of the derivative (states, inputs, parameters only).
        observed: algebraic variable name -> explicit expression.
        outputs: measured output name -> explicit expression.
        owner: state name -> component whose equation defines its derivative.
        equation_text: state name -> that equation as the user wrote it.
        aliases: eliminated variable name -> the expression it was replaced by.
        der_coefficient: state name -> ``a`` in its equation ``a·der(x) + g = 0`` (parameters
            only; 1 where it is not a parameter expression). A term ``Δ`` added to the right-hand
            side of that equation changes ``der(x)`` by ``Δ / a``, so ``a·correction`` is the
            correction in the units of the equation's terms (e.g. W for a heat balance).
        equations: state name -> the user's equation defining its derivative.
    """

    name: str
    states: list[Variable]
    parameters: list[Variable]
    inputs: list[Variable]
    rhs: dict[str, sp.Expr]
    observed: dict[str, sp.Expr]
    outputs: dict[str, sp.Expr]
    owner: dict[str, str] = field(default_factory=dict)
    equation_text: dict[str, str] = field(default_factory=dict)
    aliases: dict[str, sp.Expr] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    der_coefficient: dict[str, sp.Expr] = field(default_factory=dict)
    equations: dict[str, Equation] = field(default_factory=dict)

    @property
    def state_names(self) -> list[str]:
        return [v.name for v in self.states]

    @property
    def parameter_names(self) -> list[str]:
        return [v.name for v in self.parameters]

    @property
    def input_names(self) -> list[str]:
        return [v.name for v in self.inputs]

    @property
    def output_names(self) -> list[str]:
        return list(self.outputs)

    def summary(self) -> str:
        return (
            f"model {self.name!r}: {len(self.states)} states, {len(self.observed)} observed "
            f"(algebraic) variables, {len(self.inputs)} inputs, {len(self.parameters)} parameters, "
            f"{len(self.outputs)} measured outputs"
        )


def _alias_target(residual: sp.Expr, eliminable: set[sp.Symbol]) -> tuple[sp.Symbol, sp.Expr] | None:
    """If ``residual = 0`` says ``v = ±w`` or ``v = known``, return (v, replacement)."""
    expr = sp.expand(residual)
    terms = sp.Add.make_args(expr)
    if len(terms) > 2:
        return None
    parts: list[tuple[sp.Expr, sp.Expr]] = [t.as_coeff_Mul() for t in terms]
    cand = [(c, s) for c, s in parts if s in eliminable and c in (1, -1)]
    if not cand:
        return None
    # prefer eliminating an algebraic variable over a derivative symbol
    cand.sort(key=lambda cs: cs[1].name.startswith("der("))
    coeff, v = cand[0]
    rest = expr - coeff * v
    if rest.free_symbols & {v}:
        return None
    # rest must be ±symbol or a constant / known symbol (not a product of unknowns)
    if len(sp.Add.make_args(rest)) > 1:
        return None
    c_rest, s_rest = rest.as_coeff_Mul() if rest != 0 else (sp.Integer(0), sp.Integer(1))
    if rest != 0 and not (s_rest.is_Symbol or s_rest == 1):
        return None
    if rest != 0 and s_rest.is_Symbol and c_rest not in (1, -1):
        return None
    return v, sp.expand(-rest / coeff)


def simplify(model: Declared) -> SimplifiedModel:
    """Reduce ``model`` to an explicit ODE plus observed equations (see module docstring)."""
    states = model.of_kind("state")
    if not states:
        raise ModelError(f"model {model.name!r} has no states; declare at least one with state()")
    algebraic = model.of_kind("algebraic")
    ders = {v.name: sp.Symbol(der_name(v.name), real=True) for v in states}
    unknowns: set[sp.Symbol] = {v.symbol for v in algebraic} | set(ders.values())

    eqs: list[Equation] = list(model.equations) + model.connection_equations()
    if len(eqs) != len(unknowns):
        used = set().union(*(e.residual.free_symbols for e in eqs)) if eqs else set()
        undetermined = sorted(s.name for s in unknowns if s not in used)
        hint = f"; never used in an equation: {undetermined}" if undetermined else ""
        raise ModelError(
            f"model {model.name!r} must have one equation per unknown (state derivatives and "
            f"algebraic variables), but has {len(eqs)} equations for {len(unknowns)} unknowns{hint}"
        )

    # 1. alias elimination -----------------------------------------------------------------------
    subs: dict[sp.Symbol, sp.Expr] = {}
    remaining: list[tuple[Equation, sp.Expr]] = []
    pending = [(e, e.residual) for e in eqs]
    changed = True
    while changed:
        changed = False
        nxt: list[tuple[Equation, sp.Expr]] = []
        for eq, res in pending:
            res = res.xreplace(subs)
            if res == 0:
                raise ModelError(
                    f"model {model.name!r}: equation {eq} is redundant after alias elimination "
                    "(it repeats another equation)"
                )
            hit = _alias_target(res, unknowns - set(subs))
            if hit is None:
                nxt.append((eq, res))
                continue
            v, repl = hit
            repl = repl.xreplace(subs)
            subs = {k: val.xreplace({v: repl}) for k, val in subs.items()}
            subs[v] = repl
            changed = True
        pending = nxt
    remaining = [(eq, res.xreplace(subs)) for eq, res in pending]
    left = [u for u in unknowns if u not in subs]

    # 2. matching + BLT ---------------------------------------------------------------------------
    graph = nx.Graph()
    eq_nodes = [("eq", i) for i in range(len(remaining))]
    graph.add_nodes_from(eq_nodes, bipartite=0)
    graph.add_nodes_from(left, bipartite=1)
    for i, (_, res) in enumerate(remaining):
        for s in res.free_symbols & set(left):
            graph.add_edge(("eq", i), s)
    matching = nx.bipartite.hopcroft_karp_matching(graph, top_nodes=eq_nodes)
    unmatched_eqs = [remaining[i][0] for i in range(len(remaining)) if ("eq", i) not in matching]
    if unmatched_eqs:
        unmatched_vars = sorted(s.name for s in left if s not in matching)
        listing = "\n  ".join(str(e) for e in unmatched_eqs)
        raise ModelError(
            f"model {model.name!r} is structurally singular: these equations determine no unknown "
            f"of their own (unknowns left undetermined: {unmatched_vars}):\n  {listing}"
        )
    dep = nx.DiGraph()
    dep.add_nodes_from(range(len(remaining)))
    var_of = {i: matching[("eq", i)] for i in range(len(remaining))}
    eq_of = {v: i for i, v in var_of.items()}
    for i, (_, res) in enumerate(remaining):
        for s in res.free_symbols & set(left):
            j = eq_of[s]
            if j != i:
                dep.add_edge(j, i)  # equation j must be solved before i
    cond = nx.condensation(dep)

    # 3. solve blocks in order --------------------------------------------------------------------
    solved: dict[sp.Symbol, sp.Expr] = {}
    solved_by: dict[sp.Symbol, Equation] = {}
    for block in nx.topological_sort(cond):
        members = sorted(cond.nodes[block]["members"])
        block_eqs = [remaining[i][1].xreplace(solved) for i in members]
        block_vars = [var_of[i] for i in members]
        sol = _solve_block(model.name, [remaining[i][0] for i in members], block_eqs, block_vars)
        for v, e in sol.items():
            solved[v] = e
        for i in members:
            solved_by[var_of[i]] = remaining[i][0]

    # resolve aliases against solved unknowns
    full: dict[sp.Symbol, sp.Expr] = dict(solved)
    for v, e in subs.items():
        full[v] = e.xreplace(solved)

    rhs = {name: full[sym] for name, sym in ders.items()}
    observed = {v.name: full[v.symbol] for v in algebraic}
    outputs = {}
    for name, out in model.outputs.items():
        outputs[name] = out.expr.xreplace(full)
    owner: dict[str, str] = {}
    text: dict[str, str] = {}
    defining: dict[str, Equation] = {}
    by_der = {sym: name for name, sym in ders.items()}
    for sym, eq in solved_by.items():
        if sym in by_der:
            defining[by_der[sym]] = eq
    for name, sym in ders.items():
        if name not in defining:  # derivative eliminated as an alias: find the equation naming it
            for eq in eqs:
                if sym in eq.residual.free_symbols:
                    defining[name] = eq
                    break
    param_syms = {v.symbol for v in model.of_kind("parameter")}
    coefficient: dict[str, sp.Expr] = {}
    for name, eq in defining.items():
        owner[name], text[name] = eq.owner, str(eq)
        a = sp.diff(eq.residual, ders[name])
        coefficient[name] = a if a != 0 and a.free_symbols <= param_syms else sp.Integer(1)
    units = {v.name: v.unit for v in model.variables.values()}
    units.update({o.name: o.unit for o in model.outputs.values()})
    return SimplifiedModel(
        name=model.name,
        states=states,
        parameters=model.of_kind("parameter"),
        inputs=model.of_kind("input"),
        rhs=rhs,
        observed=observed,
        outputs=outputs,
        owner=owner,
        equation_text=text,
        aliases={k.name: v for k, v in subs.items()},
        units=units,
        der_coefficient=coefficient,
        equations=defining,
    )


#: blocks solved in this process, by their residuals and unknowns (most recent last): a corrected
#: model or a formula tried after another shares most of its blocks with the model built before
_SOLVED: Recent[dict[sp.Symbol, sp.Expr]] = Recent(4096)


def _solve_block(
    model_name: str, eqs: list[Equation], residuals: list[sp.Expr], unknowns: list[sp.Symbol]
) -> dict[sp.Symbol, sp.Expr]:
    """The block's ``unknowns`` solved from its ``residuals`` (errors name ``model_name`` and list ``eqs``)."""
    return dict(_SOLVED.get((tuple(residuals), tuple(unknowns)),
                            lambda: _solve_block_anew(model_name, eqs, residuals, unknowns)))


def _solve_block_anew(
    model_name: str, eqs: list[Equation], residuals: list[sp.Expr], unknowns: list[sp.Symbol]
) -> dict[sp.Symbol, sp.Expr]:
    listing = "\n  ".join(str(e) for e in eqs)
    names = [u.name for u in unknowns]
    if len(unknowns) == 1:
        (u,), (r,) = unknowns, residuals
        coeff = sp.diff(r, u)
        if u not in coeff.free_symbols:
            if coeff == 0:
                raise ModelError(
                    f"model {model_name!r}: equation cannot be solved for {names[0]}:\n  {listing}"
                )
            return {u: -r.xreplace({u: 0}) / coeff}
        sols = sp.solve(r, u, dict=False)
        if len(sols) != 1:
            raise ModelError(
                f"model {model_name!r}: equation must have exactly one solution for {names[0]}, "
                f"but has {len(sols)}:\n  {listing}"
            )
        return {u: sols[0]}
    try:
        a, b = sp.linear_eq_to_matrix(residuals, unknowns)
    except NonlinearError:
        raise ModelError(
            f"model {model_name!r}: the algebraic loop in {names} is nonlinear; physmend solves "
            f"algebraic loops only when they are linear. Equations:\n  {listing}"
        ) from None
    if a.det() == 0:
        raise ModelError(
            f"model {model_name!r}: the algebraic loop in {names} is singular (its equations are "
            f"linearly dependent):\n  {listing}"
        )
    x = a.LUsolve(b)
    return {u: sp.together(x[i]) for i, u in enumerate(unknowns)}
