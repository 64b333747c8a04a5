"""
The paper's fixed numbers: the means and standard deviations of Table 1 (multi-agent, 300K steps) and Table 2
(single-agent), our variant names for its columns, and the fixed reference scores that normalize returns across
tasks.
"""

#: The budget at which the paper reports every task (its Table 1 and 2)
PAPER_STEPS = 300_000

#: Paper Table 1 (multi-agent, 300K steps) and Table 2 (single-agent): (mean, std) of the team return
PAPER_RESULTS: dict[str, dict[str, tuple[float, float]]] = {
    "sb3_sera/HalfCheetah-6x1-v0": {
        "SERA": (5520, 711), "Ensemble Mean": (4831, 721), "IET": (4608, 783),
        "MASAC": (4500, 802), "MATD3": (3815, 912), "MAPPO": (3623, 812),
    },
    "sb3_sera/Pusher-3p-v0": {
        "SERA": (-27, 8), "Ensemble Mean": (-30, 7), "IET": (-29, 9),
        "MASAC": (-31, 8), "MATD3": (-50, 11), "MAPPO": (-57, 13),
    },
    "sb3_sera/Hopper-3x1-v0": {
        "SERA": (2380, 519), "Ensemble Mean": (2190, 611), "IET": (1701, 600),
        "MASAC": (1530, 200), "MATD3": (840, 400), "MAPPO": (790, 100),
    },
    "sb3_sera/Multiwalker-v0": {
        "SERA": (-27.4, 5), "Ensemble Mean": (-39, 5), "IET": (-46.5, 5),
        "MASAC": (-51, 10), "MATD3": (-56, 10), "MAPPO": (-60.3, 10),
    },
    "sb3_sera/SimpleSpread-v0": {
        "SERA": (-9, 2), "Ensemble Mean": (-13, 2.3), "IET": (-14, 4),
        "MASAC": (-16, 5.1), "MATD3": (-17.5, 6), "MAPPO": (-18, 2),
    },
    "Ant-v5": {"SERA": (1983.7, 602), "SUNRISE": (1530, 605), "ACE": (890, 654)},
    "HalfCheetah-v5": {"SERA": (6056, 439), "SUNRISE": (5613, 570), "ACE": (3923, 480)},
    "Humanoid-v5": {"SERA": (4982.6, 510), "SUNRISE": (4515.3, 600), "ACE": (3908.6, 582)},
}  # fmt: skip


#: Our variant names for the paper's columns
PAPER_NAMES = {
    "serasac": "SERA", "ensemble_mean": "Ensemble Mean", "masac": "MASAC", "matd3": "MATD3", "mappo": "MAPPO",
    "sera_nolr": "SERA-NoLR", "sera_median": "SERA-Median", "sunrise": "SUNRISE", "ace": "ACE", "iet": "IET",
}  # fmt: skip


def paper_value(env_id: str, variant: str) -> tuple[float, float] | None:
    """The paper's (mean, std) at :data:`PAPER_STEPS` for one of our variants on a task, or None where it has none."""
    return PAPER_RESULTS.get(env_id, {}).get(PAPER_NAMES.get(variant, ""))


def paper_reference(env_id: str) -> tuple[float, float] | None:
    """
    Fixed reference scores of a task for normalizing across tasks: the lowest mean of the paper's columns and SERA's
    mean at 300K (None for a task the paper does not report). Fixed, so that adding a variant changes no score.
    """
    paper = PAPER_RESULTS.get(env_id)
    if not paper or "SERA" not in paper:
        return None
    return min(mean for mean, _ in paper.values()), paper["SERA"][0]
