"""Print the nodes' parameter tables from params/*.yaml (the documented source of truth).

python scripts/params_tables.py > /tmp/params.md
"""

import re
from pathlib import Path

PARAMS = Path(__file__).resolve().parents[1] / "params"
LINE = re.compile(r"^\s{4}(\w+):\s*(.*?)\s*#\s*(.*)$")


def tables() -> str:
    out = []
    for name in ("simulator", "estimator", "evaluator", "player", "robot_estimator"):
        out.append(f"**`{name}`** (`params/{name}.yaml`)\n\n| parameter | default | meaning |\n|---|---|---|")
        for line in (PARAMS / f"{name}.yaml").read_text().splitlines():
            m = LINE.match(line)
            if m:
                key, default, doc = m.groups()
                out.append(f"| `{key}` | `{default}` | {doc.replace('|', '/')} |")
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(tables())
