"""mkdocs hook: generate the table of methods from the library itself."""

import diffrax_vi as dvi


def _row(name, solver, explicit, forces):
    order = solver.order(None)
    symmetric = isinstance(solver, dvi.AbstractSymmetricSolver)
    symplectic = isinstance(solver, dvi.AbstractSymplecticSolver)
    return (
        f"| `{name}` | {order if order is not None else '2, or 1 (see below)'} | "
        f"{explicit} | {'yes' if symmetric else 'no'} | "
        f"{'yes' if symplectic else 'presymplectic on S'} | {forces} |"
    )


def methods_table() -> str:
    sv = dvi.StormerVerlet()
    rows = [
        _row("StormerVerlet()", sv, "explicit", "1"),
        _row(
            "TrapezoidalVI()",
            dvi.TrapezoidalVI(),
            "explicit if separable, else implicit",
            "1 if separable; else 2 per Newton iteration",
        ),
        _row("MidpointVI()", dvi.MidpointVI(), "implicit", "1 per Newton iteration"),
    ]
    for s in (2, 3, 4):
        rows.append(
            _row(
                f"GaussVPRK({s})",
                dvi.GaussVPRK(s),
                "implicit",
                f"{s} per Newton iteration",
            )
        )
    for s in (3, 4):
        rows.append(
            _row(
                f"LobattoVPRK({s})",
                dvi.LobattoVPRK(s),
                "implicit",
                f"{s} per Newton iteration",
            )
        )
    for scheme in ("yoshida4", "suzuki4", "kahan_li6", "kahan_li8"):
        solver = dvi.Composition(sv, scheme)
        rows.append(
            _row(
                f'Composition(StormerVerlet(), "{scheme}")',
                solver,
                "explicit",
                str(len(solver.scheme.coefficients)),
            )
        )
    nested = dvi.Composition(dvi.Composition(sv, "triple_jump"), "triple_jump")
    rows.append(
        _row(
            'Composition(Composition(StormerVerlet(), "triple_jump"), "triple_jump")',
            nested,
            "explicit",
            str(len(nested.scheme.coefficients) * len(nested.base.scheme.coefficients)),
        )
    )
    rows.append(
        _row(
            "LinearizedVI(velocity=...)",
            dvi.LinearizedVI(),
            "one linear solve",
            "1 force and 1 Jacobian of the DEL residual",
        )
    )
    header = (
        "| method | order | explicit / implicit | symmetric | symplectic "
        "| force evaluations per step |\n|---|---|---|---|---|---|\n"
    )
    return header + "\n".join(rows)


def on_page_markdown(markdown, page, config, files):
    return markdown.replace("<!-- methods-table -->", methods_table())
