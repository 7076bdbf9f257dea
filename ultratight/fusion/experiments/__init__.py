"""The paper experiments of the integration filters (Fang 2017, Cai et al. 2020, Sun et al. 2012,
Duan et al. 2024): each simulates its paper's sensors and runs its filters, behind the interface of
``ultratight.receiver.cli.experiments`` (load, run_one, summarize, write_outputs)."""
