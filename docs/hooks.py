"""mkdocs hooks: generate the table of methods from the library itself, and turn
every formula into MathML while the site is built, so that pages render their
mathematics with no script and no network."""

import html
import pathlib
import re

import diffrax_vi as dvi
import latex2mathml.converter


def _row(name, solver, explicit, forces):
    order = solver.order(None)
    symmetric = isinstance(solver, dvi.AbstractComposableSolver) and solver.symmetric
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
        _row("LGVI()", dvi.LGVI(), "implicit (3 unknowns)", "1 torque (rigid bodies)")
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


RESULTS = pathlib.Path(__file__).parent.parent / "benchmarks" / "results"
_RESULTS_FILE = re.compile(r'<!-- results: (\S+)(?: from "([^"]+)")? -->')


def _results_block(match):
    """A results file as its command printed it, without the file's `# ` header;
    with `from "TEXT"`, only the paragraph that starts with a line starting TEXT."""
    lines = (RESULTS / match.group(1)).read_text().splitlines()
    if match.group(2):
        start = [line.startswith(match.group(2)) for line in lines].index(True)
        blank = [not line.strip() for line in lines[start:]] + [True]
        lines = lines[start : start + blank.index(True)]
    printed = "\n".join(line for line in lines if not line.startswith("# "))
    return f"```text\n{printed}\n```"


_INCLUDE = re.compile(r"<!-- include: (\S+) -->")


def _markdown_block(match):
    """A Markdown results file as written (its tables rendered), without its title
    line."""
    lines = (RESULTS / match.group(1)).read_text().splitlines()
    return "\n".join(line for line in lines if not line.startswith("# "))


def solvers_table() -> str:
    """`study.SOLVERS`: each name and the solver it makes."""
    from diffrax_vi.study import SOLVERS

    def describe(solver):
        if isinstance(solver, dvi.Composition):
            scheme = solver.scheme
            return (
                f"`Composition({solver.base!r}, ...)`: order {scheme.order}, "
                f"{len(scheme.coefficients)} substeps ({scheme.reference})"
            )
        return f"`{solver!r}`"

    rows = [f"| `{name}` | {describe(make())} |" for name, make in SOLVERS.items()]
    return "| name | solver |\n|---|---|\n" + "\n".join(rows)


def scenes_table() -> str:
    """`scenes.SCENES`: each name, its function and whether it has a monitor."""
    from diffrax_vi.scenes import MONITORED, SCENES

    rows = [
        f"| `{name}` | [`diffrax_vi.scenes.{make.__name__}`][] | "
        f"{'yes' if name in MONITORED else ''} |"
        for name, make in SCENES.items()
    ]
    return "| name | made by | step-size monitor |\n|---|---|---|\n" + "\n".join(rows)


def on_page_markdown(markdown, page, config, files):
    markdown = markdown.replace("<!-- methods-table -->", methods_table())
    markdown = markdown.replace("<!-- solvers-table -->", solvers_table())
    markdown = markdown.replace("<!-- scenes-table -->", scenes_table())
    markdown = _INCLUDE.sub(_markdown_block, markdown)
    return _RESULTS_FILE.sub(_results_block, markdown)


# pymdownx.arithmatex (generic mode) wraps inline maths as \( \) in a span and
# display maths as \[ \] in a div.
_MATH = re.compile(
    r'<(span|div) class="arithmatex">\s*\\[(\[](.*?)\\[)\]]\s*</\1>', re.S
)


def _mathml(match):
    display = "block" if match.group(1) == "div" else "inline"
    tex = html.unescape(match.group(2))
    return latex2mathml.converter.convert(tex, display=display)


def on_page_content(html_text, page, config, files):
    html_text = _MATH.sub(_mathml, html_text)
    if 'class="arithmatex"' in html_text:
        raise ValueError(f"{page.file.src_path}: a formula was left as TeX")
    return html_text


# The site must load nothing from the network: no script, stylesheet, font or
# image from another host.
_REMOTE = re.compile(
    r'<(?:script|link|img|iframe)\b[^>]*\b(?:src|href)="(?:https?:)?//[^"]*"'
)


def on_post_page(output, page, config):
    remote = _REMOTE.search(output)
    if remote:
        where = page.file.src_path
        raise ValueError(f"{where} loads from the network: {remote.group(0)}")
    return output
