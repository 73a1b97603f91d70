"""The data ddfuse ships: the sample bags, their configs, and the configs of the known real bags.

It is the package ``ddfuse.data`` (``data/`` of the checkout in an editable install, a copy in
site-packages in a regular one), read through ``importlib.resources``. ``config_for`` is the
rule every command uses to find a bag's config when none is given.
"""

from __future__ import annotations

from pathlib import Path

from ddfuse.estimation.errors import DdfuseError

__all__ = ["CONFIGS", "DATA", "SAMPLE_BAG", "config_for", "data_dir"]


def data_dir() -> Path:
    """Where ddfuse's shipped data is: the package ``ddfuse.data`` (the sample bags and their
    configs, ``configs/<stem>.yaml`` of the known real bags), which is ``data/`` of the checkout
    in an editable install and a copy in site-packages in a regular one."""
    from importlib.resources import files

    return Path(str(files("ddfuse.data")))


DATA = data_dir()
SAMPLE_BAG = DATA / "sample_husky.bag"
CONFIGS = DATA / "configs"


def config_for(bag: Path, given: Path | None) -> Path:
    """The config: ``given`` (-c) if not None, else the bag's path with .yaml (for the storage
    file inside a ROS 2 bag directory, ``h.mcap/h.mcap``, the directory's: ``h.yaml``, as
    ``ddfuse simulate`` writes it), else the one ddfuse ships for the known real bags
    (``CONFIGS/<stem>.yaml``). DdfuseError naming the bag when there is none, or no bag."""
    if given is not None:
        return given
    if not Path(bag).exists():  # say that, not that its config is missing
        raise DdfuseError(f"{bag}: no such bag (file or ROS 2 directory)")
    cands = [bag.with_suffix(".yaml")]
    if (bag.parent / "metadata.yaml").is_file():  # a file inside a ROS 2 bag directory
        cands.append(bag.parent.with_suffix(".yaml"))
    for cand in (*cands, CONFIGS / f"{bag.stem}.yaml"):
        if cand.is_file():
            return cand
    raise DdfuseError(f"{bag}: no config given (-c) and none at {bag.with_suffix('.yaml')}; "
                      f"'ddfuse inspect {bag}' suggests one")
