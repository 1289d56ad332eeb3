"""Write a copy of a data root whose BallPlay humanoid has a stiffer drive on
some joints, for A/Bs of a per-joint PD stiffness without a new setting.

    python3 stages/scale_kp.py DATA_ROOT OUT_ROOT FACTOR arms|rest

OUT_ROOT gets a symbolic link to every entry of DATA_ROOT except
`assets/mjcf/mocap_humanoid.xml`, which is rewritten with the `stiffness`
(kp) of the chosen hinges multiplied by FACTOR (a finite number above 0,
written back exactly); `damping` (kd) and every
other attribute are left as they are. `arms` picks every hinge of the
shoulder subtrees (the shoulders, elbows, wrists and fingers: 36 joints of
three hinges each, the joints of `train.residual_scale_joints = "arms"`);
`rest` picks the other 16 joints (hips, knees, ankles, toes, torso, spines,
chest, neck, head, thoraxes). Train and evaluate with `--data-root OUT_ROOT`
(docs/training.md, "A stiffer drive on some joints"). The edit is textual,
one `<joint .../>` element at a time, so the file keeps its layout.
"""

import math
import os
import re
import sys
import xml.etree.ElementTree as ET

MODEL = os.path.join("assets", "mjcf", "mocap_humanoid.xml")


def number(v):
    """`v` as MJCF text that reads back to the same float: whole numbers as
    integers (the shipped files write kp so), others by the shortest
    round-trip form (`%g` would keep only six significant digits)."""
    return str(int(v)) if v.is_integer() else repr(v)


def shoulder_hinges(root):
    """Names of the hinges in every body subtree whose body name holds `Shoulder`."""
    names = set()

    def walk(body, inside):
        inside = inside or "Shoulder" in body.get("name", "")
        if inside:
            names.update(j.get("name") for j in body.findall("joint"))
        for child in body.findall("body"):
            walk(child, inside)

    for world in root.iter("worldbody"):
        for body in world.findall("body"):
            walk(body, False)
    return names


def link_tree(src, dst, keep):
    """Mirror `src` into `dst` with links, descending only along `keep` (a relative path)."""
    os.makedirs(dst, exist_ok=True)
    head = keep.split(os.sep, 1)
    for name in sorted(os.listdir(src)):
        if name == head[0] and len(head) == 2:
            link_tree(os.path.join(src, name), os.path.join(dst, name), head[1])
        elif name != head[0]:
            os.symlink(os.path.abspath(os.path.join(src, name)), os.path.join(dst, name))


def main():
    if len(sys.argv) != 5 or sys.argv[4] not in ("arms", "rest"):
        sys.exit(__doc__)
    src, dst, which = sys.argv[1], sys.argv[2], sys.argv[4]
    try:
        factor = float(sys.argv[3])
    except ValueError:
        factor = math.nan
    if not (math.isfinite(factor) and factor > 0):
        sys.exit(f"FACTOR {sys.argv[3]!r}: give a finite number above 0")
    model = os.path.join(src, MODEL)
    if not os.path.isfile(model):
        sys.exit(f"{model}: no such file (is {src} a data root?)")
    if os.path.exists(dst):
        sys.exit(f"{dst}: already exists; give a new folder")
    text = open(model).read()
    arms = shoulder_hinges(ET.fromstring(text))
    if not arms:
        sys.exit(f"{model}: no body named *Shoulder*")
    scaled = 0

    def edit(m):
        nonlocal scaled
        element = m.group(0)
        name = re.search(r'name="([^"]+)"', element)
        if name is None or 'stiffness="' not in element:
            return element
        if (name.group(1) in arms) != (which == "arms"):
            return element
        scaled += 1
        return re.sub(
            r'stiffness="([^"]+)"',
            lambda s: f'stiffness="{number(float(s.group(1)) * factor)}"',
            element,
        )

    out = re.sub(r"<joint [^>]*>", edit, text)
    link_tree(src, dst, MODEL)
    with open(os.path.join(dst, MODEL), "w") as f:
        f.write(out)
    print(f"{dst}: {scaled} hinges' stiffness x {factor:g} ({which})")


if __name__ == "__main__":
    main()
