"""dslearn's Hydra plugins: the matrix sweeper (``hydra/sweeper=matrix``), which runs only the combinations of a
sweep whose method fits the scenario (:mod:`.matrix_sweeper`). Hydra finds it in the ``hydra_plugins``
namespace package."""
