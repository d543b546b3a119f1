import csv
import json
import pathlib


def markdown_table(rows: list[dict]) -> str:
    """Records as a Markdown table: errors in scientific notation, seconds to three
    significant digits (a short run's too), `None` (a setting that does not apply)
    as a dash."""
    header = list(rows[0])

    def cell(key, value):
        if value is None:
            return "–"
        if isinstance(value, float):
            return f"{value:.3g}" if key.endswith("_s") else f"{value:.3e}"
        return str(value)

    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(cell(k, v) for k, v in r.items()) + " |" for r in rows]
    return "\n".join(lines)


def write_records(
    out: pathlib.Path, stem: str, rows: list[dict], **json_fields
) -> list[pathlib.Path]:
    """Write `rows` to `<stem>.csv`, and `rows` with `json_fields` to `<stem>.json`."""
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"{stem}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with open(out / f"{stem}.json", "w") as f:
        json.dump(dict(json_fields, summary=rows), f)
    return [out / f"{stem}.csv", out / f"{stem}.json"]
