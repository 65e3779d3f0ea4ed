"""Training and scoring a run: its settings (``config``, ``backbones``, ``checks``), the run
folder (``run``), the loop (``trainer``) with its losses and per-image appearance, and the
scores (``metrics``, ``evaluation``). docs/training.md."""
