"""ddfuse's shipped data, installed as the package ``ddfuse.data`` (pyproject.toml maps this
directory to it): the simulated sample bags with their configs and landmark map, and
``configs/<stem>.yaml`` for the known real bags. ``ddfuse.evaluation.shipped`` finds it (README.md
here says what each file is)."""
