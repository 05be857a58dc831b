from pathlib import Path

from cadpu.plots import plot_log, plotted_terms


def test_a_log_of_the_snapped_objective_plots_its_term_and_not_the_empty_emd(tmp_path: Path) -> None:
    rows = [{"step": "1", "emd": "nan", "snapped_chamfer": "0.05", "regularizer": "0.6", "adversarial": "0",
             "discriminator": "0"},
            {"step": "2", "emd": "nan", "snapped_chamfer": "0.04", "regularizer": "0.5", "adversarial": "0",
             "discriminator": "0"}]
    assert plotted_terms(rows) == ["snapped_chamfer", "regularizer", "adversarial", "discriminator"]
    # a log begun before the snapped column: its EMD, no snapped column
    assert plotted_terms([{"step": "1", "emd": "0.1", "regularizer": "0.6"}]) == ["emd", "regularizer"]
    log = tmp_path / "log.csv"
    log.write_text("step,emd,snapped_chamfer,regularizer,adversarial,discriminator\n1,nan,0.05,0.6,0,0\n2,nan,0.04,0.5,0,0\n")
    plot_log(log, tmp_path / "losses.png")
    assert (tmp_path / "losses.png").stat().st_size > 0
