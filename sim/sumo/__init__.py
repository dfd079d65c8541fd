"""SUMO for scale (issue 37): road networks (generated grids and random networks, and the sand table's
own network exported with its junction and lane ids), reproducible demand per seed, run through
libsumo with no rendering. The wheels (`eclipse-sumo`, `libsumo`, `sumolib`) are pinned in
pyproject.toml; `tools.py` finds their programs."""
