#!/usr/bin/env python3
"""Generate the warehouse KBs: ``Object.owl``, ``Location.owl``, ``Capability.owl``.

    python tools/gen_warehouse.py --products 1000 --robots 9 --seed 7 --out ontologies/
    python tools/gen_warehouse.py --products 100000 --format ttl --out /tmp/kb100k-ttl

Output is deterministic: the same arguments give byte-identical files.  The
logic lives in :mod:`coapkb.world.generator` and :mod:`coapkb.world.ontologies`;
this is only its command line.  ``--format ttl`` or ``nt`` writes the same
graphs as Turtle or N-Triples (``Object.ttl``, ...), converted from the
RDF/XML with pyoxigraph.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from coapkb.world.generator import WarehouseSpec, generate
from coapkb.world.ontologies import write_ontologies

SUFFIXES = {"ttl": ".ttl", "nt": ".nt"}


def convert(owl: Path, out: Path, fmt: str) -> Path:
    """``owl`` (RDF/XML) as Turtle or N-Triples in ``out``, same stem; streamed."""
    import pyoxigraph as ox

    prefixes = {}
    for event, item in ET.iterparse(owl, events=("start-ns", "start")):
        if event == "start":
            break
        if item[0]:
            prefixes[item[0]] = item[1]
    target = out / (owl.stem + SUFFIXES[fmt])
    tmp = target.with_name(target.name + ".tmp")
    base = target.with_suffix(".owl").resolve().as_uri()  # as if the RDF/XML file were in out
    triples = (q.triple for q in ox.parse(path=owl, format=ox.RdfFormat.RDF_XML, base_iri=base))
    if fmt == "ttl":
        ox.serialize(triples, output=tmp, format=ox.RdfFormat.TURTLE, prefixes=prefixes)
    else:
        ox.serialize(triples, output=tmp, format=ox.RdfFormat.N_TRIPLES)
    tmp.replace(target)
    return target


def main(argv: list[str] | None = None) -> int:
    defaults = WarehouseSpec()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--products", type=int, default=defaults.products)
    p.add_argument("--robots", type=int, default=defaults.robots)
    p.add_argument("--seed", type=int, default=defaults.seed)
    p.add_argument("--aisles", type=int, default=defaults.aisles)
    p.add_argument("--racks-per-aisle", type=int, default=defaults.racks_per_aisle)
    p.add_argument("--bins-per-rack", type=int, default=defaults.bins_per_rack)
    p.add_argument("--out", type=Path, default=Path("ontologies"), help="output directory")
    p.add_argument("--format", choices=["owl", "ttl", "nt"], default="owl",
                   help="RDF/XML (.owl, default), Turtle (.ttl) or N-Triples (.nt)")
    p.add_argument("-q", "--quiet", action="store_true")
    args = p.parse_args(argv)
    try:
        spec = WarehouseSpec(
            products=args.products,
            aisles=args.aisles,
            racks_per_aisle=args.racks_per_aisle,
            bins_per_rack=args.bins_per_rack,
            robots=args.robots,
            seed=args.seed,
        )
    except ValueError as exc:
        p.error(str(exc))
    start = time.perf_counter()
    if args.format == "owl":
        written = write_ontologies(spec, args.out)
    else:
        args.out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="gen_warehouse-") as tmp:
            owl = write_ontologies(spec, tmp)
            written = {name: convert(path, args.out, args.format) for name, path in owl.items()}
    elapsed = time.perf_counter() - start
    if not args.quiet:
        for path in written.values():
            print(f"{path}  {path.stat().st_size:,} bytes")
        print(f"generated in {elapsed:.2f} s")
        wh = generate(spec)
        bag = wh.product("Gucci_bag_14")
        print(
            f"Gucci_bag_14: aisle {bag.position.aisle}, rack {bag.position.rack}, bin {bag.bin_no}, "
            f"picked by {bag.grip}"
        )
        for r in wh.robots:
            print(
                f"{r.robot_id}: can_pick={','.join(r.can_pick)} payload={r.payload_kg} kg "
                f"home=({r.home.aisle},{r.home.rack})"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
