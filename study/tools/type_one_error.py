"""
The type-I error of a claim's test (``sera_study.results.stats.decision_p_value``): how often it rejects at alpha
0.05 when the two arms' means are equal, at 10 runs against 5 with standard deviations 2.5x apart, for normal data and
for skewed data (a centred gamma of shape 4, skewness 1), the larger spread on either arm; beside it, the studentized
permutation test and Welch's t-test alone.

    python study/tools/type_one_error.py --trials 5000 --seed 12345
"""

import argparse

import numpy as np

from sera_study.results.stats import decision_p_value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=5000, help="simulated data sets per case")
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--alpha", type=float, default=0.05)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    print(f"{args.trials} data sets a case, 10 runs against 5, equal means, alpha {args.alpha}")
    print("| data | larger spread on | decision | studentized permutation | Welch's t |\n|---|---|---|---|---|")
    for distribution in ("normal", "skewed"):
        for larger in ("5-run arm", "10-run arm"):
            spreads = (1.0, 2.5) if larger == "5-run arm" else (2.5, 1.0)

            def draw(size: int, spread: float, distribution: str = distribution) -> np.ndarray:
                if distribution == "normal":
                    return rng.normal(0.0, spread, size)
                return (rng.gamma(4.0, 1.0, size) - 4.0) / 2.0 * spread

            rejected = np.zeros(3)
            for _ in range(args.trials):
                rejected += np.array(decision_p_value(draw(10, spreads[0]), draw(5, spreads[1]))) < args.alpha
            rates = " | ".join(f"{rate:.4f}" for rate in rejected / args.trials)
            print(f"| {distribution} | {larger} | {rates} |", flush=True)


if __name__ == "__main__":
    main()
