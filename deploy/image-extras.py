"""Print the optional extras of pyproject.toml that the container image carries, comma separated:
every extra except those only developers need (test, dev, docs). The image is the whole product
(viewer, ROS 2 bridge, recordings, ...), so a new runtime extra is in it without editing anything
here. Read by deploy/lock-constraints.sh (to pin their dependencies) and by the Dockerfile (to
install them), so the two never disagree.

Usage: python3 deploy/image-extras.py [pyproject.toml] [--requirements]
  --requirements   print the requirements (dependencies + those extras, one per line) instead
"""
import re
import sys
import tomllib

NOT_IN_IMAGE = {"test", "tests", "dev", "docs"}

args = [a for a in sys.argv[1:] if not a.startswith("--")]
with open(args[0] if args else "pyproject.toml", "rb") as f:
    project = tomllib.load(f)["project"]
name = re.sub(r"[-_.]+", "-", project["name"]).lower()
optional = project.get("optional-dependencies", {})
extras = [e for e in optional if e not in NOT_IN_IMAGE]
if "--requirements" not in sys.argv:
    print(",".join(extras))
    sys.exit(0)

seen: set[str] = set()
out: list[str] = []


def add(reqs: list[str]) -> None:
    for r in reqs:
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(?:\[([^\]]*)\])?", r)
        if m and re.sub(r"[-_.]+", "-", m.group(1)).lower() == name:  # ballbot-vision[x]: its extras
            for e in (m.group(2) or "").split(","):
                if e.strip() and e.strip() not in seen:
                    seen.add(e.strip())
                    add(optional.get(e.strip(), []))
        elif r not in out:
            out.append(r)


add(project.get("dependencies", []))
for e in extras:
    if e not in seen:
        seen.add(e)
        add(optional[e])
print("\n".join(out))
