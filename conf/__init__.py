"""dslearn's Hydra configs, shipped inside the package as ``dslearn.conf`` (search path ``pkg://dslearn.conf``).

The source of these files is the repository's top-level ``conf/`` folder (mapped to this package in
``pyproject.toml``); add your own config folders with ``hydra.searchpath`` (see the README), not here.
"""
