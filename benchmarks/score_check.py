"""Can a sharpness score find a per-pixel latency? The true map's score against the best constant's.

For each of the accuracy suite's intensity-dependent cases (per-pixel delay, photoreceptor), scores the
EDI latent of the true latency map and of every constant latency whose window holds events, and counts
the cases where the score prefers the true map. A score that does not cannot lead any search over maps
(the spatial fit, or a richer family) to the truth. See :mod:`evlatcorr.benchmark.score_check`.

    python benchmarks/score_check.py --split dev            # 20 cases, about 2 minutes on 2 cores
    python benchmarks/score_check.py --split dev --scores sparsity etf
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.accuracy import make_cases  # noqa: E402
from evlatcorr.benchmark.score_check import CHECKED_SCORES, MAP_MODELS, check_case, checks_to_markdown  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "dev", num_help="first N cases of the split (before keeping map cases)")
    p.add_argument("--scores", nargs="+", choices=CHECKED_SCORES, default=list(CHECKED_SCORES))
    p.add_argument("--out", type=Path, default=Path("outputs/score_check.md"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    cases = [c for c in make_cases(args.split, args.num, tuple(args.size)) if c.latency_model in MAP_MODELS]
    if not cases:
        p.error(f"no per-pixel latency case among the first {args.num} of split {args.split}")
    _setup.check_out_folder(p, args.out.parent)
    rows = []
    for i, case in enumerate(cases, 1):
        rows.append(check_case(case, scores=tuple(args.scores)))
        wins = [n for n, s in rows[-1]["scores"].items() if s["true_wins"]]
        print(f"[{i}/{len(cases)}] {case.name}: true map sharper for {', '.join(wins) or 'no score'}", flush=True)
    text = (f"# Sharpness scores against the true latency map ({args.split} split, {len(cases)} cases)\n\n"
            + checks_to_markdown(rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print("\n" + text + f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
