"""
rl-zoo3 registration, as SBX registers with the zoo: :func:`register` adds this package's algorithms to rl-zoo3's
algorithm table and their hyperparameter search spaces to its ``-optimize`` tables, and :data:`HYPERPARAMS_DIR`
holds their zoo files (``serasac.yml``, ``masac.yml``, ...). A training script of one's own::

    from rl_zoo3.train import train

    from sb3_sera.zoo import register

    register()
    train()  # python train.py --algo serasac --env HalfCheetah-v5 --conf-file <HYPERPARAMS_DIR>/serasac.yml

The study's ``sb3-sera train`` does this and passes the file itself. rl-zoo3 comes with the library's ``zoo`` extra,
``pip install "sb3-sera[zoo]"``: importing this module does not need it, :func:`register` does.
"""

from pathlib import Path

from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_sera.ace import ACE
from sb3_sera.common.capabilities import capabilities
from sb3_sera.common.extras import needs_zoo_extra
from sb3_sera.ctde.algorithms import MADDPG, MAPPO, MASAC, MATD3
from sb3_sera.iet import IET
from sb3_sera.sera import SERASAC
from sb3_sera.sunrise import SUNRISE

#: The package's algorithms under their zoo names
ALGOS: dict[str, type[BaseAlgorithm]] = {
    "serasac": SERASAC,
    "masac": MASAC,
    "matd3": MATD3,
    "maddpg": MADDPG,
    "mappo": MAPPO,
    "sunrise": SUNRISE,
    "ace": ACE,
    "iet": IET,
}


def _hyperparams_dir() -> Path:
    """
    ``sb3_sera/hyperparams/`` in an installed wheel (where the build maps them), else the repository's top-level
    ``hyperparams/`` (a checkout or an editable install), their one source.
    """
    installed = Path(__file__).resolve().parent / "hyperparams"
    return installed if installed.is_dir() else Path(__file__).resolve().parents[1] / "hyperparams"


#: One YAML file per algorithm, keyed by env id (rl-zoo3's format), shipped with the package
HYPERPARAMS_DIR = _hyperparams_dir()


def register() -> None:
    """
    Add :data:`ALGOS` to rl-zoo3's algorithm table (``rl_zoo3.utils.ALGOS``), and to its ``-optimize`` sampler and
    converter tables each algorithm's own search space (its ``tuning``) or that of the SB3 algorithm it tunes like
    (its ``tunes_like``); idempotent.

    :raises ImportError: where rl-zoo3 is not installed (the ``zoo`` extra: ``pip install "sb3-sera[zoo]"``)
    """
    with needs_zoo_extra("sb3_sera.zoo.register()"):
        from rl_zoo3 import hyperparams_opt, utils

    utils.ALGOS.update(ALGOS)
    samplers, converters = hyperparams_opt.HYPERPARAMS_SAMPLER, hyperparams_opt.HYPERPARAMS_CONVERTER
    for name, algo in ALGOS.items():
        declared = capabilities(algo)
        if declared["tuning"]:
            samplers[name], converters[name] = declared["tuning"]
        elif declared["tunes_like"]:
            samplers[name], converters[name] = samplers[declared["tunes_like"]], converters[declared["tunes_like"]]
