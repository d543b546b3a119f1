r"""What keeps XLA from compiling a time-stepping loop as one function on CPU.

XLA's CPU compiler runs a `while` loop as one compiled function only if its body is
small (the threshold `import diffrax_vi` raises, see `_xla.py`) *and* holds no custom
call (a LAPACK routine, a host callback), no custom fusion and no scatter. A matrix
product with a side of more than three can become such a fusion (`kind=kCustom`, a
YNNPACK `__ynn_fusion`); so can the batched products that `jax.vmap` or a Jacobian
makes of a small `R @ x`. A scatter comes from `x.at[i].set(...)` or from the
derivative of indexing by an array, `x[np.array([1, 2])]` (a gather). The loop is
then broken into kernels dispatched one by one, each step paying for every one of
them: about a hundred times the arithmetic of a rigid-body step. The cure is to
write small products as elementwise sums (`jnp.sum(R * x, axis=-1)` for `R @ x`),
small solves in closed form, and a selection of rows as static slices
(`x[1:4]`, `jnp.concatenate([x[2:3], x[0:1]])`).

This module reads the optimised HLO text of a compiled program and lists what, inside
its loops, breaks them.
"""

import re

import jax


_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%?([\w.\-]+)\s.*\{\s*$")
_CALLED = re.compile(
    r"(?:body|condition|calls|to_apply|true_computation|false_computation)"
    r"=%?([\w.\-]+)"
)
_BRANCHES = re.compile(r"branch_computations=\{([^}]*)\}")
_WHILE_BODY = re.compile(r"\swhile\(.*?body=%?([\w.\-]+)")
_WHILE_CONDITION = re.compile(r"\swhile\(.*?condition=%?([\w.\-]+)")
_SCATTER = re.compile(r"\sscatter\(")


def _computations(hlo: str) -> dict[str, list[str]]:
    computations: dict[str, list[str]] = {}
    current = None
    for line in hlo.splitlines():
        if current is None:
            match = _COMPUTATION.match(line)
            if match is not None:
                current = match.group(1)
                computations[current] = []
        elif line.strip() == "}":
            current = None
        else:
            computations[current].append(line)
    return computations


def _called(line: str) -> list[str]:
    names = _CALLED.findall(line)
    for group in _BRANCHES.findall(line):
        names += [name.strip().lstrip("%") for name in group.split(",")]
    return names


def loop_breakers(hlo: str) -> list[str]:
    """The instructions inside the `while` loops of an optimised HLO module (the text
    of `jax.jit(f).lower(...).compile().as_text()`) that keep XLA on CPU from
    compiling the loop as one function: custom calls, custom fusions and scatters.
    Empty for a loop at its floor.

    **Arguments:**

    - `hlo`: the optimised HLO text.

    **Returns:**

    Each offending instruction, shortened to its name, kind or target, and the JAX
    operation it came from.
    """
    computations = _computations(hlo)
    roots = []
    for lines in computations.values():
        for line in lines:
            roots += _WHILE_BODY.findall(line) + _WHILE_CONDITION.findall(line)
    seen: set[str] = set()
    stack = list(roots)
    while stack:
        name = stack.pop()
        if name in seen or name not in computations:
            continue
        seen.add(name)
        for line in computations[name]:
            stack += _called(line)
    found = []
    for name in sorted(seen):
        for line in computations[name]:
            if (
                "custom-call(" in line
                or "kind=kCustom" in line
                or _SCATTER.search(line)
            ):
                found.append(_describe(line))
    return found


def kernels_outside_loops(hlo: str) -> int:
    """The fused kernels of an optimised HLO module's entry computation, outside
    every loop: XLA on CPU compiles each of them on its own (about 10 ms each on a
    2-core machine), where a loop it compiles whole is one function."""
    entry = hlo[hlo.index("ENTRY") :]
    return entry[: entry.index("\n}")].count(" fusion(")


def _describe(line: str) -> str:
    name = line.strip().removeprefix("ROOT ").split(" ", 1)[0]
    target = re.search(r'custom_call_target="([^"]+)"', line)
    kind = re.search(r'"kind":"([^"]+)"', line)
    op = re.search(r'op_name="([^"]+)"', line)
    if target:
        what = target.group(1)
    elif _SCATTER.search(line):
        what = "scatter"
    else:
        what = kind.group(1) if kind else "kCustom"
    return f"{name} ({what}) from {op.group(1) if op else 'an unnamed operation'}"


def compiled_loop_breakers(fn, *args, **kwargs) -> list[str]:
    """[`diffrax_vi.diagnostics.loop_breakers`][] of `jax.jit(fn)` compiled for
    `args`: check that a `diffeqsolve` of your own Lagrangian compiles its
    time-stepping loop whole (on CPU).

    !!! example

        ```python
        solve = lambda y0: diffrax.diffeqsolve(term, solver, 0.0, 1.0, 0.01, y0).ys
        assert diffrax_vi.diagnostics.compiled_loop_breakers(solve, y0) == []
        ```

    A custom fusion named `__ynn_fusion` comes from a small matrix product: write it
    as an elementwise sum. A custom call to `lapack_…` comes from a linear solve or a
    decomposition in the loop: write it in closed form. A `scatter` comes from
    `.at[...]` updates or from differentiating indexing by an array: take the rows
    by static slices.
    """
    compiled = jax.jit(fn).lower(*args, **kwargs).compile()
    return loop_breakers(compiled.as_text())
