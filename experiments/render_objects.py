"""Every procedural object in one picture (topocut.sim.render.render_objects; docs/sim.md).

    python experiments/render_objects.py --objects docs/img/objects.png
"""
import argparse

from topocut.sim.render import render_objects


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", metavar="PNG", required=True, help="draw every object into this PNG")
    args = ap.parse_args(argv)
    print(render_objects(args.objects))


if __name__ == "__main__":
    main()
