"""Where a large KB's load time goes: ``KnowledgeBase.load`` and its parts.

    .venv/bin/python tools/gen_warehouse.py --products 100000 --out /tmp/kb100k
    .venv/bin/python tools/gen_warehouse.py --products 100000 --format ttl --out /tmp/kb100k-ttl
    .venv/bin/python tools/gen_warehouse.py --products 100000 --format nt --out /tmp/kb100k-nt
    .venv/bin/python -m experiments.kb_load --dirs /tmp/kb100k /tmp/kb100k-ttl /tmp/kb100k-nt

Every measurement runs in a fresh process (its peak RSS is its own); each is
repeated ``--repeat`` times, interleaved, and the minimum kept (the machine
may be shared).  Variants, per directory (its ``*.owl``/``*.ttl``/``*.nt``
files, loaded in name order):

* ``KnowledgeBase.load``: the loader as a robot runs it (read, ETag hash,
  prefixes, parse and insert, triple count);
* ``index build`` / ``index open``: ``KnowledgeBase.load(index_dir=...)``,
  the on-disk index a robot keeps with ``kb_index``: its first start (a
  fresh index directory each run) and every later one (the index built
  once before the rounds); peak RSS is the process's;
* ``Store.load bytes`` / ``Store.load path`` / ``Store.bulk_load bytes`` /
  ``Store.bulk_load path``: pyoxigraph alone, one file after another into an
  in-memory ``Store``;
* ``... lenient``: the same with ``lenient=True`` (for comparison only: it
  lets invalid IRIs and language tags in, so the loader does not use it);
* ``parse only``: ``pyoxigraph.parse`` iterated, no store (an upper bound of
  the parser's own time: it also builds a Python object per triple);
* ``read + blake2b``: reading the files and hashing them for the ETag.

After a ``KnowledgeBase`` variant's load it also times the named queries
of a task: ``first_query_us``, the first ``object-exists`` run (thread CPU
time, as a robot's ``KBResources`` records it: under
``QueryLimits.inline_below_s``, 2 ms, the query's later runs go inline on the
event loop), and ``task_queries_us``, one product's three task queries
(median over products).  ``--dirs ontologies`` gives the committed warehouse.

Prints a table and writes ``experiments/results/kb_load.csv``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments.common import experiment_argv, write_csv

ROOT = Path(__file__).resolve().parent.parent

SUFFIXES = {".owl": "RDF/XML", ".rdf": "RDF/XML", ".ttl": "Turtle", ".nt": "N-Triples"}

VARIANTS = [
    "KnowledgeBase.load",
    "index build",
    "index open",
    "Store.load bytes",
    "Store.load path",
    "Store.bulk_load bytes",
    "Store.bulk_load path",
    "Store.load bytes lenient",
    "parse only",
    "parse only lenient",
    "read + blake2b",
]

CSV_FIELDS = ["variant", "format", "dir", "files_mb", "triples", "runs", "min_s", "median_s", "triples_per_s",
              "peak_rss_mb", "first_query_us", "task_queries_us"]

#: A task's three named queries about one product (Query_1-3), timed after a
#: KnowledgeBase variant's load: what an on-disk index costs per task.
TASK_QUERIES = ("object-exists", "object-location", "object-features")
QUERY_PRODUCTS = 200


def kb_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix in SUFFIXES)


def measure(variant: str, directory: Path, index_dir: Path) -> dict[str, float]:
    """One measurement in this process; returns seconds, triples, peak RSS."""
    import pyoxigraph as ox

    from coapkb.kb.store import KnowledgeBase

    formats = {"RDF/XML": ox.RdfFormat.RDF_XML, "Turtle": ox.RdfFormat.TURTLE, "N-Triples": ox.RdfFormat.N_TRIPLES}
    paths = kb_files(directory)
    lenient = variant.endswith(" lenient")
    started = time.perf_counter()
    triples = 0
    kb = None
    if variant == "KnowledgeBase.load":
        kb = KnowledgeBase.load(paths)
        triples = kb.triple_count
    elif variant == "index build":
        with tempfile.TemporaryDirectory(dir=index_dir) as fresh:
            triples = KnowledgeBase.load(paths, index_dir=fresh).triple_count
    elif variant == "index open":
        kb = KnowledgeBase.load(paths, index_dir=index_dir)
        triples = kb.triple_count
    elif variant.startswith("Store."):
        store = ox.Store()
        method = store.bulk_load if variant.startswith("Store.bulk_load") else store.load
        for p in paths:
            kw = {"format": formats[SUFFIXES[p.suffix]], "base_iri": p.resolve().as_uri(), "lenient": lenient}
            if " path" in variant:
                method(path=p, **kw)
            else:
                method(p.read_bytes(), **kw)
        triples = len(store)
    elif variant.startswith("parse only"):
        for p in paths:
            for _ in ox.parse(path=p, format=formats[SUFFIXES[p.suffix]], base_iri=p.resolve().as_uri(),
                              lenient=lenient):
                triples += 1
    elif variant == "read + blake2b":
        digest = hashlib.blake2b(digest_size=8)
        for p in paths:
            digest.update(p.read_bytes())
    else:
        raise ValueError(variant)
    seconds = time.perf_counter() - started
    first_query_us, task_queries_us = time_task_queries(kb) if kb is not None else (None, None)
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {"s": seconds, "triples": triples, "peak_rss_mb": peak_kib / 1024, "first_query_us": first_query_us,
            "task_queries_us": task_queries_us}


def time_task_queries(kb: object) -> tuple[float, float]:
    """Microseconds of the first ``object-exists`` run after the load (thread
    CPU time, the measure of the inline fast path) and of one product's three
    task queries (median over products)."""
    from coapkb.kb.named_queries import named_queries_for
    from coapkb.world import OBJECT_NS

    queries = {q.name: q for q in named_queries_for(kb.names)}  # type: ignore[attr-defined]
    if not all(name in queries for name in TASK_QUERIES):
        return float("nan"), float("nan")
    names = kb.query(  # type: ignore[attr-defined]
        f"PREFIX o: <{OBJECT_NS}> SELECT ?name WHERE {{ ?p o:Product_name ?name }}", row_limit=QUERY_PRODUCTS
    ).rows
    started = time.thread_time()
    kb.query(queries["object-exists"].render({"name": str(names[0][0])}))  # type: ignore[attr-defined]
    first_us = (time.thread_time() - started) * 1e6
    per_product = []
    for (name,) in names:
        started = time.perf_counter()
        for query in TASK_QUERIES:
            kb.query(queries[query].render({"name": str(name)}))  # type: ignore[attr-defined]
        per_product.append((time.perf_counter() - started) * 1e6)
    return first_us, statistics.median(per_product)


def _median_us(results: list[dict[str, float]], key: str) -> float | str:
    times = [r[key] for r in results if r.get(key) is not None]
    return round(statistics.median(times)) if times else ""


def inline_below_us() -> int:
    from coapkb.kb.limits import QueryLimits

    return round(QueryLimits().inline_below_s * 1e6)


def run_one(variant: str, directory: Path, index_dir: Path) -> dict[str, float]:
    out = subprocess.run(experiment_argv("kb_load", "--one", variant, str(directory), str(index_dir)), check=True,
                         capture_output=True, text=True, cwd=ROOT)
    return json.loads(out.stdout)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.kb_load",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dirs", type=Path, nargs="+", default=[Path("/tmp/kb100k")])
    p.add_argument("--variants", nargs="+", default=VARIANTS, choices=VARIANTS, metavar="VARIANT")
    p.add_argument("--repeat", type=int, default=3, help="runs per variant and directory (minimum kept)")
    p.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "kb_load.csv")
    p.add_argument("--one", nargs=3, metavar=("VARIANT", "DIR", "INDEX_DIR"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one is not None:
        print(json.dumps(measure(args.one[0], Path(args.one[1]), Path(args.one[2]))))
        return 0
    with tempfile.TemporaryDirectory(prefix="kb-index-") as index_dir:
        return sweep(p, args, Path(index_dir))


def sweep(p: argparse.ArgumentParser, args: argparse.Namespace, index_dir: Path) -> int:
    jobs = []
    for directory in args.dirs:
        files = kb_files(directory)
        if not files:
            p.error(f"{directory}: no *.owl, *.ttl or *.nt files")
        fmt = "+".join(sorted({SUFFIXES[f.suffix] for f in files}))
        size_mb = sum(f.stat().st_size for f in files) / 1e6
        for variant in args.variants:
            if "bulk_load path" in variant and fmt != "RDF/XML":
                continue  # same picture as for RDF/XML; keeps the run short
            jobs.append((variant, directory, fmt, size_mb))
        if "index open" in args.variants:
            run_one("index open", directory, index_dir)  # builds it: the rounds then open it
    runs: dict[tuple[str, Path], list[dict[str, float]]] = {(v, d): [] for v, d, _, _ in jobs}
    for round_no in range(args.repeat):  # interleaved: other load on the machine hits every variant alike
        for variant, directory, _, _ in jobs:
            runs[variant, directory].append(run_one(variant, directory, index_dir))
            print(f"round {round_no + 1}: {variant:26} {directory}: {runs[variant, directory][-1]['s']:.2f} s",
                  file=sys.stderr, flush=True)
    rows = []
    for variant, directory, fmt, size_mb in jobs:
        results = runs[variant, directory]
        best = min(r["s"] for r in results)
        triples = int(max(r["triples"] for r in results))
        rows.append({
            "variant": variant, "format": fmt, "dir": str(directory), "files_mb": round(size_mb),
            "triples": triples or "", "runs": len(results), "min_s": round(best, 2),
            "median_s": round(statistics.median(r["s"] for r in results), 2),
            "triples_per_s": round(triples / best) if triples else "",
            "peak_rss_mb": round(min(r["peak_rss_mb"] for r in results)),
            "first_query_us": _median_us(results, "first_query_us"),
            "task_queries_us": _median_us(results, "task_queries_us"),
        })
    print(f"{'variant':26} {'format':10} {'MB':>4} {'triples':>9} {'min s':>6} {'med s':>6} {'triples/s':>10} "
          f"{'RSS MB':>7} {'first query us':>14} {'task queries us':>15}")
    for r in rows:
        tps = f"{r['triples_per_s']:,}" if r["triples_per_s"] else ""
        print(f"{r['variant']:26} {r['format']:10} {r['files_mb']:>4} {r['triples'] or '':>9} {r['min_s']:>6} "
              f"{r['median_s']:>6} {tps:>10} {r['peak_rss_mb']:>7} {r['first_query_us']:>14} "
              f"{r['task_queries_us']:>15}")
    print(f"(a named query whose first run takes under {inline_below_us()} us runs inline afterwards)")
    write_csv(args.out, CSV_FIELDS, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
