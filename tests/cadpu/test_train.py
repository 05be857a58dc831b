import dataclasses
import re
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import numpy as np
import pytest
import torch

from cadpu import losses
from cadpu.data import DataSpec, PatchSet, load_or_build
from cadpu.train import Recipe, Trainer, main, read_yaml, recipe_changes, samples_seen, train
from cadpu.weights import load_generator

TINY_DATA = DataSpec(meshes=1, patches_per_mesh=4, scanline_share=0.5, first_seed=3)


@pytest.fixture(scope="module")
def tiny_patches(tmp_path_factory: pytest.TempPathFactory) -> tuple[PatchSet, Path]:
    cache = tmp_path_factory.mktemp("cache")
    return load_or_build(TINY_DATA, cache, progress=False), cache


def _recipe(cache: Path, output: Path, **changes: object) -> Recipe:
    base = Recipe(steps=20, batch_size=4, lr_generator=3e-3, lr_discriminator=3e-4, decay_every=1000,
                  adversarial_from=1000, checkpoint_every=1000, threads=0, data=TINY_DATA,
                  cache_dir=str(cache), output=str(output))
    return replace(base, **changes)


def _fixed_emd(trainer: Trainer, patches: PatchSet) -> float:
    """EMD of the generator on the un-augmented patches, with a fixed expansion draw."""
    trainer.generator.eval()
    with torch.no_grad():
        pred, _ = trainer.generator(torch.from_numpy(patches.inputs), generator=torch.Generator().manual_seed(1))
        return losses.emd(pred, torch.from_numpy(patches.truth)).item()


def test_a_few_training_steps_lower_the_emd(tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    patches, cache = tiny_patches
    trainer = Trainer(_recipe(cache, tmp_path), patches, torch.device("cpu"))
    batch = tuple(torch.from_numpy(a) for a in (patches.inputs, patches.truth, patches.truth_normals))
    before = _fixed_emd(trainer, patches)
    for _ in range(30):  # measured: 0.945-0.951 of the start after 30 steps, over 3 seeds
        terms = trainer.step(batch)
    assert set(terms) >= {"emd", "regularizer", "adversarial", "generator", "discriminator"}
    assert _fixed_emd(trainer, patches) < 0.97 * before


def test_the_objective_sums_the_emd_over_points_as_equation_4() -> None:
    emd, regularizer, adversarial = torch.tensor(0.1), torch.tensor(0.4), torch.tensor(0.2)
    value = losses.generator_objective(emd, regularizer, adversarial, points=1024, beta=0.15, gamma=0.005)
    assert value.item() == pytest.approx(1024 * 0.1 + 0.15 * 0.4 + 0.0025 * 0.2)
    # twice the points: the EMD term doubles, the averaged regularizer does not
    doubled = losses.generator_objective(emd, regularizer, adversarial, points=2048, beta=0.15, gamma=0.005)
    assert (doubled - value).item() == pytest.approx(1024 * 0.1)


@pytest.fixture
def one_thread() -> Iterator[None]:
    """torch on one thread for the test (a multi-threaded BLAS may sum in another order from run to
    run on a busy machine, and one flipped EMD match then moves a weight by a whole Adam step)."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_an_interrupted_run_resumes_to_the_same_weights(tiny_patches: tuple[PatchSet, Path], tmp_path: Path,
                                                        one_thread: None, capsys: pytest.CaptureFixture[str]) -> None:
    _, cache = tiny_patches
    whole = _recipe(cache, tmp_path / "whole", steps=4, checkpoint_every=2, adversarial_from=2, threads=1)
    train(whole, progress=False)
    parts = replace(whole, output=str(tmp_path / "parts"))
    # out of time after the first step: it stops there with a checkpoint, though checkpoints are
    # due every 2 steps (it ran on to step 2 before the limit was checked every step)
    train(parts, progress=False, max_seconds=0.0)
    log_rows = (tmp_path / "parts" / "log.csv").read_text().strip().splitlines()
    assert len(log_rows) == 1 + 1
    assert "stopped by --max-seconds at step 1 of 4; continue with --resume" in capsys.readouterr().err
    train(parts, progress=False, resume=True)
    log_rows = (tmp_path / "parts" / "log.csv").read_text().strip().splitlines()
    assert [row.split(",")[0] for row in log_rows[1:]] == ["1", "2", "3", "4"]
    expected = load_generator(tmp_path / "whole" / "generator.pt")[0].state_dict()
    resumed = load_generator(tmp_path / "parts" / "generator.pt")[0].state_dict()
    for name, tensor in expected.items():  # float noise only: one step of Adam moves weights by ~3e-3
        np.testing.assert_allclose(resumed[name].numpy(), tensor.numpy(), rtol=0, atol=2e-4, err_msg=name)


def _logged_rates(log: Path) -> list[float]:
    rows = log.read_text().strip().splitlines()
    column = rows[0].split(",").index("lr_g")
    return [float(row.split(",")[column]) for row in rows[1:]]


@pytest.mark.parametrize("schedule", ["step", "cosine"])
def test_the_learning_rate_follows_the_recipe_across_a_resume(tiny_patches: tuple[PatchSet, Path],
                                                              tmp_path: Path, schedule: str) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=4, checkpoint_every=2, decay_every=2, decay=0.5,
                     lr_schedule=schedule, lr_final_share=0.1)
    train(recipe, progress=False, max_seconds=0.0)  # stops after step 1
    train(recipe, progress=False, resume=True)
    # the rate logged after step s is the one step s + 1 uses
    expected = [3e-3 * recipe.lr_factor(step) for step in range(1, 5)]
    assert _logged_rates(tmp_path / "log.csv") == pytest.approx(expected, rel=1e-5)
    if schedule == "cosine":
        assert recipe.lr_factor(0) == 1.0 and recipe.lr_factor(4) == pytest.approx(0.1)
        assert recipe.lr_factor(2) == pytest.approx(0.55)
    else:
        assert expected == pytest.approx([3e-3, 1.5e-3, 1.5e-3, 0.75e-3])


def test_a_cosine_with_cycles_anneals_at_every_cycle_end_then_restarts() -> None:
    recipe = Recipe(steps=10, lr_schedule="cosine", lr_final_share=0.1, lr_cycle=4)
    factors = [recipe.lr_factor(step) for step in range(10)]
    # steps 0-3 fall from the full rate, then 4-7 again, 8-9 start a third cycle
    assert factors[0] == factors[4] == factors[8] == 1.0
    assert factors[1:4] == pytest.approx(factors[5:8]) and factors[2] == pytest.approx(0.55)
    assert all(a > b for a, b in zip(factors[:3], factors[1:4]))
    assert Recipe(steps=8, lr_schedule="cosine", lr_final_share=0.1).lr_factor(4) == pytest.approx(0.55)
    with pytest.raises(ValueError, match="lr_cycle"):
        Recipe(lr_schedule="cosine", lr_cycle=-1)
    with pytest.raises(ValueError, match="lr_cycle restarts the cosine"):
        Recipe(lr_schedule="step", lr_cycle=1000)
    with pytest.raises(ValueError, match="ratio must be 4: the training pairs are 256 -> 1024 points"):
        Recipe(ratio=16)  # refused before any data is made, not an EMD shape error after


def test_a_run_resumed_under_another_schedule_takes_up_the_new_curve(tiny_patches: tuple[PatchSet, Path],
                                                                     tmp_path: Path) -> None:
    _, cache = tiny_patches
    stepped = _recipe(cache, tmp_path, steps=4, checkpoint_every=2)
    train(stepped, progress=False, max_seconds=0.0)
    annealed = replace(stepped, lr_schedule="cosine", lr_final_share=0.1)
    train(annealed, progress=False, resume=True)
    assert _logged_rates(tmp_path / "log.csv")[1:] == pytest.approx(
        [3e-3 * annealed.lr_factor(step) for step in range(2, 5)], rel=1e-5)


@pytest.mark.parametrize("reduction, factor", [("sum", 1024), ("mean", 1)])
def test_the_recipe_chooses_how_the_emd_is_weighed(tiny_patches: tuple[PatchSet, Path], tmp_path: Path,
                                                   reduction: str, factor: int) -> None:
    patches, cache = tiny_patches
    trainer = Trainer(_recipe(cache, tmp_path, emd_reduction=reduction), patches, torch.device("cpu"))
    terms = trainer.step()  # before the discriminator starts: no adversarial term
    assert terms["adversarial"] == 0.0
    assert terms["generator"] == pytest.approx(factor * terms["emd"] + 0.15 * terms["regularizer"], rel=1e-5)


def test_the_recipe_refuses_an_unknown_emd_reduction() -> None:
    with pytest.raises(ValueError, match="emd_reduction"):
        Recipe(emd_reduction="max")
    with pytest.raises(ValueError, match="lr_schedule"):
        Recipe(lr_schedule="linear")
    with pytest.raises(ValueError, match="emd_epsilon"):
        Recipe(emd_epsilon=-1.0)


def test_the_exact_and_the_auction_emd_train_alike(tiny_patches: tuple[PatchSet, Path]) -> None:
    patches, _ = tiny_patches
    terms = []
    for epsilon in (0.0, 1e-4):
        trainer = Trainer(Recipe(batch_size=2, threads=1, emd_epsilon=epsilon), patches, torch.device("cpu"))
        terms.append(trainer.step())
    assert terms[0]["emd"] <= terms[1]["emd"] <= terms[0]["emd"] + 1e-4 + 1e-6
    assert terms[1]["regularizer"] == pytest.approx(terms[0]["regularizer"], rel=1e-5)


def test_a_step_with_the_discriminator_updates_both_networks_as_the_plain_gan_step(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    """The step scores the generator's output without the discriminator's own gradients: the
    same updates as the plain step below, which computes and then discards them."""
    patches, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, adversarial_from=0, gamma=0.5, seed=4)
    batch = tuple(torch.from_numpy(a) for a in (patches.inputs, patches.truth, patches.truth_normals))
    trainer, reference = (Trainer(recipe, patches, torch.device("cpu")) for _ in range(2))
    trainer.step(batch)

    inputs, truth, normals = batch
    reference.generator.train()
    pred, _ = reference.generator(inputs, generator=reference.sampler)
    distances = losses.pred_target_distances(pred, truth)
    total = losses.generator_objective(losses.emd(pred, truth, recipe.emd_epsilon, distances),
                                       losses.curvature_regularizer(pred, truth, normals, distances=distances),
                                       losses.generator_adversarial(reference.discriminator(pred)),
                                       pred.shape[1], recipe.beta, recipe.gamma)
    reference.opt_g.zero_grad(set_to_none=True)
    total.backward()
    reference.opt_g.step()
    d_loss = losses.discriminator_loss(reference.discriminator(truth), reference.discriminator(pred.detach()))
    reference.opt_d.zero_grad(set_to_none=True)
    d_loss.backward()
    reference.opt_d.step()

    for ours, theirs in ((trainer.generator, reference.generator), (trainer.discriminator, reference.discriminator)):
        for (name, a), (_, b) in zip(ours.named_parameters(), theirs.named_parameters()):
            assert torch.allclose(a, b, atol=1e-6), name
    assert all(p.requires_grad for p in trainer.discriminator.parameters())


def test_a_checkpoint_is_never_overwritten_by_a_fresh_start(tiny_patches: tuple[PatchSet, Path],
                                                             tmp_path: Path) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path / "run", steps=2, checkpoint_every=1,
                     checkpoint=str(tmp_path / "kept" / "run.pt"))
    with pytest.raises(FileNotFoundError, match="no checkpoint to resume"):
        train(recipe, progress=False, resume=True)
    train(recipe, progress=False)
    assert (tmp_path / "kept" / "run.pt").is_file() and not (tmp_path / "run" / "checkpoint.pt").exists()
    with pytest.raises(FileExistsError, match="--resume"):
        train(recipe, progress=False)


def test_a_resumed_run_cannot_change_the_network(tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=3, checkpoint_every=1)
    train(recipe, progress=False, max_seconds=0.0)
    saved_recipe = (tmp_path / "recipe.yaml").read_text()
    with pytest.raises(ValueError, match=r"checkpoint's network has alpha 0.5 \(the recipe says 1.0\)"):
        train(replace(recipe, alpha=1.0), progress=False, resume=True)
    assert (tmp_path / "recipe.yaml").read_text() == saved_recipe  # refused before anything was written


def test_a_resumed_run_keeps_what_it_changed_in_the_weights_provenance(tiny_patches: tuple[PatchSet, Path],
                                                                     tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=3, checkpoint_every=1)
    train(recipe, progress=False, max_seconds=0.0)
    meta = load_generator(train(replace(recipe, beta=0.3, steps=4), progress=False, resume=True))[2]
    assert meta["segments"][0].get("recipe_changes") is None
    assert meta["segments"][-1]["recipe_changes"] == {"steps": [3, 4], "beta": [0.15, 0.3]}
    assert "with a changed recipe: steps 3 -> 4, beta 0.15 -> 0.3" in capsys.readouterr().err


def _exits_2_saying(capsys: pytest.CaptureFixture[str], pattern: str, argv: list[str]) -> None:
    """`main(argv)` exits with status 2 (bad input, as kitti-pu's) and one stderr line matching `pattern`."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert re.search(pattern, err) and "Traceback" not in err, err


def test_a_recipe_value_of_the_wrong_kind_is_refused_naming_its_key(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match="recipe: steps must be an integer, got 'abc'"):
        Recipe(steps="abc")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"lr_generator must be a number, got '1e-3' \(a number in quotes is text"):
        Recipe(lr_generator="1e-3")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="recipe: threads must be an integer, got True"):
        Recipe(threads=True)
    with pytest.raises(ValueError, match="recipe data: streets must be an integer, got 'many'"):
        Recipe(data=DataSpec(streets="many"))  # type: ignore[arg-type]
    assert Recipe(lr_generator=1, init_weights=None).lr_generator == 1  # an int is a number
    with pytest.raises(ValueError, match="recipe: steps must be at least 1, got 0"):
        Recipe(steps=0)  # it wrote the untrained generator as a weights file
    with pytest.raises(ValueError, match="recipe: batch_size must be at least 1, got -2"):
        Recipe(batch_size=-2)
    with pytest.raises(ValueError, match="recipe: snapshot_every must be 0 or more, got -1"):
        Recipe(snapshot_every=-1)
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text("steps: 10\n")
    _exits_2_saying(capsys, "cadpu.train: recipe: steps must be an integer, got 'abc'", [str(recipe_file), "--set", "steps=abc"])


def test_bad_recipes_and_set_items_exit_2_naming_what_is_wrong(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text("steps: [3\n")  # a YAML parser traceback, exit 1, before
    _exits_2_saying(capsys, f"cadpu.train: {re.escape(str(recipe_file))}: not valid YAML", [str(recipe_file)])
    recipe_file.write_text("steps: 3\nsteps: 4\n")  # the last one was taken without a word
    _exits_2_saying(capsys, r"not valid YAML at line 2, column 1 \(key 'steps' given twice \(first on line 1\)\)",
                    [str(recipe_file)])
    recipe_file.write_text("steps: 3\n")
    _exits_2_saying(capsys, r"--set steps=\[3: the value is not valid YAML", [str(recipe_file), "--set", "steps=[3"])
    # torch's "Invalid learning rate: -1" named no key; a negative --max-seconds was taken
    _exits_2_saying(capsys, "recipe: lr_generator must be a number above 0, got -1",
                    [str(recipe_file), "--set", "lr_generator=-1"])
    _exits_2_saying(capsys, r"recipe: emd_epsilon must be a number, got 'nan' \(YAML writes it .nan",
                    [str(recipe_file), "--set", "emd_epsilon=nan"])
    _exits_2_saying(capsys, "--max-seconds must be 0 or more, got -5.0", [str(recipe_file), "--max-seconds", "-5"])
    _exits_2_saying(capsys, "--set steps: expected KEY=VALUE", [str(recipe_file), "--set", "steps"])
    recipe_file.write_text("data: {meshes: 0}\n")  # a TypeError from PatchSet, before
    _exits_2_saying(capsys, "meshes and streets are both 0: no training data", [str(recipe_file)])
    recipe_file.write_text("data: {meshes: 1, patches_per_mesh: 0}\n")  # "need at least one array to stack"
    _exits_2_saying(capsys, "patches_per_mesh must be at least 1", [str(recipe_file)])


def test_a_batch_larger_than_the_training_set_is_refused_before_any_step(tiny_patches: tuple[PatchSet, Path],
                                                                        tmp_path: Path) -> None:
    patches, cache = tiny_patches
    with pytest.raises(ValueError, match=f"batch_size 64 is more than the {len(patches)} training patches"):
        train(_recipe(cache, tmp_path, steps=1, batch_size=64), progress=False)


def test_a_weights_path_that_is_a_folder_is_refused_before_training(tiny_patches: tuple[PatchSet, Path],
                                                                    tmp_path: Path) -> None:
    _, cache = tiny_patches
    folder = tmp_path / "out_dir"
    folder.mkdir()
    recipe = _recipe(cache, tmp_path / "run", steps=2)
    with pytest.raises(ValueError, match=f"--weights-out: {re.escape(str(folder))} is a folder"):
        train(recipe, folder, progress=False)  # the run trained, then the rename failed, before
    assert not (tmp_path / "run" / "checkpoint.pt").exists()  # refused before any step
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_exponent_numbers_in_a_recipe_and_in_set_are_numbers(tmp_path: Path) -> None:
    # PyYAML reads 1e-3 as text (YAML 1.1 wants 1.0e-3); the recipe refused it as "not a number"
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text("lr_generator: 1e-3\nlr_discriminator: 5E-5\nsteps: 10\n")
    recipe = Recipe.from_yaml(recipe_file)
    assert (recipe.lr_generator, recipe.lr_discriminator) == (1e-3, 5e-5)
    assert Recipe.from_yaml(recipe_file, {"beta": read_yaml("2e-1")}).beta == 0.2
    assert read_yaml("'1e-3'") == "1e-3" and read_yaml("1e") == "1e"  # quoted, or not a number: text


def test_a_run_started_from_weights_counts_their_samples(tiny_patches: tuple[PatchSet, Path],
                                                         tmp_path: Path) -> None:
    _, cache = tiny_patches
    first = train(_recipe(cache, tmp_path / "first", steps=3), progress=False)
    assert load_generator(first)[2]["samples_seen"] == 3 * 4
    second = _recipe(cache, tmp_path / "second", steps=2, batch_size=2, init_weights=str(first))
    trainer = Trainer(second, tiny_patches[0], torch.device("cpu"))
    start = load_generator(first)[0].state_dict()
    for name, tensor in trainer.generator.state_dict().items():
        assert torch.equal(tensor, start[name]), name
    meta = load_generator(train(second, progress=False))[2]
    assert meta["samples_seen"] == 3 * 4 + 2 * 2
    assert meta["segments"][-1]["to_step"] == 2 and meta["segments"][-1]["hardware"]


def test_samples_seen_of_files_from_before_the_count() -> None:
    assert samples_seen({"steps": 700, "recipe": {"batch_size": 8}}) == 5600
    assert samples_seen({"samples_seen": 10, "steps": 700}) == 10


def test_samples_seen_count_each_segment_at_its_own_batch_size(tiny_patches: tuple[PatchSet, Path],
                                                                tmp_path: Path) -> None:
    patches, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=3, batch_size=2, checkpoint=str(tmp_path / "checkpoint.pt"))
    train(recipe, tmp_path / "a.pt", progress=False, patches=patches)
    train(replace(recipe, steps=5, batch_size=4), tmp_path / "b.pt", resume=True, progress=False, patches=patches)
    _, _, meta = load_generator(tmp_path / "b.pt")
    assert samples_seen(meta) == 3 * 2 + 2 * 4  # it counted all 5 steps at 4
    train(replace(recipe, steps=6, batch_size=2), tmp_path / "c.pt", resume=True, progress=False, patches=patches)
    assert samples_seen(load_generator(tmp_path / "c.pt")[2]) == 3 * 2 + 2 * 4 + 2  # and could fall


def test_a_resume_refuses_a_weights_file_as_checkpoint_and_fewer_steps_than_done(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    patches, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=3, batch_size=2, checkpoint=str(tmp_path / "checkpoint.pt"))
    train(recipe, tmp_path / "a.pt", progress=False, patches=patches)
    with pytest.raises(ValueError, match="past the recipe's steps \\(2\\); give steps of at least 3"):
        train(replace(recipe, steps=2), tmp_path / "b.pt", resume=True, progress=False, patches=patches)
    with pytest.raises(ValueError, match="not a training checkpoint of cadpu.train \\(a weights file\\?"):
        train(replace(recipe, checkpoint=str(tmp_path / "a.pt")), tmp_path / "b.pt", resume=True, progress=False,
              patches=patches)
    # a checkpoint cut short, empty or of text: torch's traceback (exit 1), or a message naming no file (a trial)
    whole = (tmp_path / "checkpoint.pt").read_bytes()
    for damaged in (whole[:len(whole) // 2], b"", b"garbage\n"):
        (tmp_path / "checkpoint.pt").write_bytes(damaged)
        with pytest.raises(ValueError, match=f"{tmp_path / 'checkpoint.pt'}: not a readable checkpoint .* delete it"):
            train(recipe, tmp_path / "b.pt", resume=True, progress=False, patches=patches)
    # a folder: found after the training (IsADirectoryError, with a temporary left beside it), before
    folder = tmp_path / "runs"
    folder.mkdir()
    with pytest.raises(ValueError, match=f"recipe checkpoint: {folder} is a folder"):
        train(replace(recipe, checkpoint=str(folder)), tmp_path / "c.pt", progress=False, patches=patches)
    assert not (tmp_path / "c.pt").exists() and not list(tmp_path.glob(".runs*"))


def test_main_says_a_bad_starting_weights_file_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "nan.pt"
    generator = load_generator("cadpu_r4")[0]
    with torch.no_grad():
        next(generator.parameters()).fill_(float("nan"))
    from cadpu.weights import write_file
    write_file(bad, generator.state_dict(), generator.config)  # as earlier versions wrote diverged runs
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text(f"steps: 1\nbatch_size: 4\ninit_weights: {bad}\ndata: {{meshes: 1, patches_per_mesh: 4}}\n"
                           f"output: {tmp_path / 'run'}\ncache_dir: {tmp_path / 'cache'}\n")
    _exits_2_saying(capsys, "cadpu.train: .*non-finite", [str(recipe_file)])


def test_an_unknown_key_given_by_set_is_named_as_set_not_as_the_file(tmp_path: Path) -> None:
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text("steps: 3\n")
    with pytest.raises(ValueError, match=r"^--set: unknown recipe key\(s\) \['stepz'\]"):
        Recipe.from_yaml(recipe_file, {"stepz": 3})
    recipe_file.write_text("stepz: 3\n")
    with pytest.raises(ValueError, match=rf"^{recipe_file}: unknown recipe key"):
        Recipe.from_yaml(recipe_file, {})
    recipe_file.write_text("steps: 3\n")  # a data key of --set was blamed on the file
    with pytest.raises(ValueError, match=r"^--set: unknown data key\(s\) \['mesh'\]"):
        Recipe.from_yaml(recipe_file, {"data": {"mesh": 2}})
    with pytest.raises(ValueError, match=r"^--set: unknown data key\(s\) \['mesh'\]"):
        Recipe.from_yaml(recipe_file, {"data.mesh": 2})


def test_set_data_key_changes_one_key_of_the_recipe_s_data(tmp_path: Path) -> None:
    recipe_file = tmp_path / "recipe.yaml"
    recipe_file.write_text("steps: 3\ndata:\n  meshes: 0\n  streets: 7\n  scene_types: [urban]\n")
    recipe = Recipe.from_yaml(recipe_file, {"data.scene_types": ["urban", "rural"], "steps": 4})
    assert (recipe.steps, recipe.data.streets, recipe.data.meshes) == (4, 7, 0)
    assert recipe.data.scene_types == ("urban", "rural")


def test_a_resume_with_nothing_left_to_train_leaves_the_weights_file_as_it_is(tiny_patches: tuple[PatchSet, Path],
                                                                              tmp_path: Path) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=2)
    written = train(recipe, progress=False)
    before = written.read_bytes()
    # it was written again with new times in its meta: a new checksum, so every pipeline frame made
    # with it counted as made by another model
    assert train(recipe, progress=False, resume=True) == written
    assert written.read_bytes() == before


def test_a_resume_with_nothing_left_to_train_rewrites_a_weights_file_of_an_earlier_step(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    # the file written when --max-seconds stopped the run at step 2 was kept, and reported as
    # written, after the run had gone on to its last step with --weights-out elsewhere
    _, cache = tiny_patches
    written = train(_recipe(cache, tmp_path, steps=2), progress=False)
    elsewhere = train(_recipe(cache, tmp_path, steps=4), tmp_path / "elsewhere.pt", progress=False, resume=True)
    assert train(_recipe(cache, tmp_path, steps=4), progress=False, resume=True) == written
    _, _, meta = load_generator(written)
    assert meta["steps"] == 4
    assert all(torch.equal(a, b) for a, b in zip(load_generator(written)[0].state_dict().values(),
                                                 load_generator(elsewhere)[0].state_dict().values()))


def test_a_resume_drops_the_log_rows_of_steps_after_the_checkpoint(tiny_patches: tuple[PatchSet, Path],
                                                                   tmp_path: Path) -> None:
    # a run interrupted after logging steps past its last checkpoint trains them again: they were
    # logged twice, and the loss plot drew both
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=4, checkpoint_every=2, threads=1)
    train(recipe, progress=False, max_seconds=0.0)  # stops at step 1, with its checkpoint
    log = tmp_path / "log.csv"
    with log.open("a") as rows:  # what the interrupted run had logged after it
        rows.write("2,9.9,0.001,1,1,1,1,1\n3,9.9,0.001,1,1,1,1,1\n")
    # and so were the scores of held-out curves and validation (a training user's trial)
    curves, validation = tmp_path / "curves.csv", tmp_path / "validation.csv"
    curves.write_text("step,samples_seen,set,metric,network,baseline\n1,8,meshes,CD,0.5,0.6\n2,16,meshes,CD,9.9,0.6\n")
    validation.write_text("step,score,best_step\n1,0.5,1\n2,9.9,2\n")
    train(recipe, progress=False, resume=True)
    steps = [row.split(",")[0] for row in log.read_text().strip().splitlines()[1:]]
    assert steps == ["1", "2", "3", "4"]
    assert "9.9" not in log.read_text()
    assert curves.read_text() == "step,samples_seen,set,metric,network,baseline\n1,8,meshes,CD,0.5,0.6\n"
    assert validation.read_text() == "step,score,best_step\n1,0.5,1\n"
    # a run started afresh (its checkpoint deleted): the earlier run's validation rows are another
    # run's; its curves are left alone unless it records its own
    (tmp_path / "checkpoint.pt").unlink()
    train(replace(recipe, steps=1), progress=False)
    assert validation.read_text().splitlines() == ["step,score,best_step"]
    assert curves.read_text() == "step,samples_seen,set,metric,network,baseline\n1,8,meshes,CD,0.5,0.6\n"


def test_a_data_key_added_since_the_checkpoint_is_not_a_change_of_the_recipe(tmp_path: Path) -> None:
    # the repository's own checkpoints, saved before data.scene_types existed, were resumed "with a
    # changed recipe" that was none, and the non-change was kept in the weights' provenance
    recipe = Recipe(data=DataSpec(meshes=0, streets=2))
    stored = dataclasses.asdict(recipe)
    del stored["data"]["scene_types"]
    assert recipe_changes(stored, recipe, tmp_path / "c.pt") == {}
    other = replace(recipe, data=replace(recipe.data, scene_types=("rural",)))
    assert list(recipe_changes(stored, other, tmp_path / "c.pt")) == ["data"]


def test_ctrl_c_before_the_steps_is_one_line_and_exit_130(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    # while a recipe built its patches (minutes of ray casting), Ctrl-C printed a 40-line
    # KeyboardInterrupt traceback and the process died by the signal (a training user's trial)
    import cadpu.train as train_module

    def building_patches(*args: object, **kwargs: object) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "train", building_patches)
    with pytest.raises(SystemExit) as stopped:
        train_module.main([str(Path(__file__).resolve().parents[2] / "configs" / "train_smoke.yaml")])
    assert stopped.value.code == 130
    assert capsys.readouterr().err == ("cadpu.train: stopped by SIGINT outside a step; the last checkpoint, if there "
                                       "is one, stands (continue with --resume)\n")


def test_ctrl_c_stops_after_the_step_with_a_checkpoint_and_the_weights(tiny_patches: tuple[PatchSet, Path],
                                                                       tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    # it ended the run where it was: a KeyboardInterrupt traceback, no weights, the steps since the
    # last checkpoint lost (and under finetune, now and then a segmentation fault at exit)
    import os
    import signal

    from cadpu.stopping import TrainingStopped

    patches, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=10, checkpoint_every=1000, threads=1)
    step = Trainer.step

    def interrupted_at_step_3(self: Trainer, *args: object) -> dict[str, float]:
        terms = step(self, *args)
        if self.step_count == 3:
            os.kill(os.getpid(), signal.SIGINT)  # as Ctrl-C in the middle of the run
        return terms

    monkeypatch.setattr(Trainer, "step", interrupted_at_step_3)
    # as in a terminal: a background job (this suite run with `&`) starts with SIGINT ignored
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(TrainingStopped, match="stopped by SIGINT after step 3") as stopped:
            train(recipe, progress=False, patches=patches)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is given back
    finally:
        signal.signal(signal.SIGINT, before)
    assert stopped.value.exit_status == 130
    assert load_generator(stopped.value.weights)[2]["steps"] == 3
    assert torch.load(recipe.checkpoint_path, weights_only=False)["step"] == 3
    monkeypatch.setattr(Trainer, "step", step)
    train(recipe, progress=False, patches=patches, resume=True)  # and --resume goes on from there
    assert load_generator(stopped.value.weights)[2]["steps"] == 10


def test_a_run_that_diverges_stops_naming_the_step_and_saves_nothing_of_it(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a learning rate of 10 made the output NaN, and the auction's bidding on NaN costs never ended
    # (signals could not stop it); weights of NaN were written with exit status 0 otherwise
    from cadpu.train import TrainingDiverged

    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=6, lr_generator=1e30, checkpoint_every=1)
    with pytest.raises(TrainingDiverged, match=r"training diverged at step \d: .* (is NaN or infinite|distances overflow)"):
        train(recipe, progress=False)
    assert not (tmp_path / "generator.pt").exists()
    checkpoint = tmp_path / "checkpoint.pt"
    if checkpoint.exists():  # a step before the divergence may have been saved: never a non-finite one
        state = torch.load(checkpoint, weights_only=False)["generator"]
        assert all(torch.isfinite(t).all() for t in state.values() if t.is_floating_point())


def test_a_run_whose_points_fly_off_without_overflowing_stops_as_diverged(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    # at a learning rate of 1 the output's distances reached 1e16, finite: the auction then bid for
    # ever, and neither Ctrl-C nor SIGTERM stopped the run (a training user's trial)
    from cadpu.train import DIVERGED_DISTANCE, TrainingDiverged, Trainer

    patches, cache = tiny_patches
    trainer = Trainer(_recipe(cache, tmp_path, steps=2), patches, torch.device("cpu"))
    inputs, truth, normals = trainer.batch()
    with pytest.raises(TrainingDiverged, match=r"training diverged at step 1: the generator's points lie up to .* "
                                               r"from the truth") as diverged:
        trainer.step((inputs, truth + 10 * DIVERGED_DISTANCE, normals))
    # it said "the last checkpoint stands" where none had been written (a researcher's trial)
    assert str(diverged.value).endswith("nothing of this step is saved, and no checkpoint was written before it")
    trainer.recipe.checkpoint_path.write_bytes(b"a checkpoint")
    with pytest.raises(TrainingDiverged, match=re.escape(f"the last checkpoint ({trainer.recipe.checkpoint_path}) stands")):
        trainer.step((inputs, truth + 10 * DIVERGED_DISTANCE, normals))


def test_a_batch_of_damaged_truth_is_named_as_such_and_overflowing_distances_as_a_divergence(
        tiny_patches: tuple[PatchSet, Path], tmp_path: Path) -> None:
    # NaN truth was reported as the generator's divergence, and distances that overflow from
    # finite points as NaN output (a reviewer's find)
    from cadpu.train import TrainingDiverged, Trainer

    patches, cache = tiny_patches
    trainer = Trainer(_recipe(cache, tmp_path, steps=2), patches, torch.device("cpu"))
    inputs, truth, normals = trainer.batch()
    damaged = truth.clone()
    damaged[0, 0, 0] = float("inf")
    with pytest.raises(ValueError, match=r"training step 1: the batch's truth points hold NaN or infinite values"):
        trainer.step((inputs, damaged, normals))
    with pytest.raises(TrainingDiverged, match=r"training diverged at step 1: the generator's points lie so far from "
                                               r"the truth that their distances overflow"):
        trainer.step((inputs, truth + 1e30, normals))


def test_weights_that_are_not_finite_are_never_written(tmp_path: Path) -> None:
    from cadpu.network import Generator
    from cadpu.weights import save

    generator = Generator()
    with torch.no_grad():
        next(generator.parameters())[0] = float("nan")
    with pytest.raises(ValueError, match="not written: 3 non-finite values .* in extractor"):
        save(generator, tmp_path / "w.pt")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("change, message", [
    ({"decay_every": 0}, "decay_every must be at least 1"),  # a ZeroDivisionError
    ({"decay": -1.0}, r"decay must be in \(0, 1\]"),  # gradient ascent, silently
    ({"beta": float("nan")}, "beta must be a finite number of 0 or more"),
    ({"gamma": float("inf")}, "gamma must be a finite number of 0 or more"),
    ({"beta": -1.0}, "beta must be a finite number of 0 or more"),
    ({"seed": -1}, "seed must be 0 or more"),  # numpy's "expected non-negative integer"
])
def test_recipe_values_that_cannot_train_are_refused_naming_the_key(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"recipe: {message}"):
        Recipe(**change)


@pytest.mark.parametrize("change, message", [({"scanline_share": 2.0}, r"scanline_share must be in \[0, 1\]"),
                                             ({"scanline_share": float("nan")}, r"scanline_share must be in \[0, 1\]"),
                                             ({"first_seed": -5}, "first_seed must be 0 or more")])
def test_data_values_that_cannot_make_patches_are_refused_naming_the_key(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"DataSpec: {message}"):
        DataSpec(**change)


def test_a_run_records_the_checksum_of_the_file_it_started_from(tiny_patches: tuple[PatchSet, Path],
                                                                  tmp_path: Path) -> None:
    from cadpu.weights import sha256_of

    _, cache = tiny_patches
    first = train(_recipe(cache, tmp_path / "a", steps=1), progress=False)
    second = train(_recipe(cache, tmp_path / "b", steps=1, init_weights=str(first)), progress=False)
    meta = load_generator(second)[2]
    assert meta["init_weights"] == str(first) and meta["init_sha256"] == sha256_of(first)


@pytest.fixture(scope="module")
def street_patches(tmp_path_factory: pytest.TempPathFactory) -> tuple[PatchSet, Path, DataSpec]:
    cache = tmp_path_factory.mktemp("streets")
    spec = DataSpec(meshes=0, streets=1, scans_per_street=1, patches_per_scan=4, scan_vertical_scale=0.15)
    return load_or_build(spec, cache, progress=False), cache, spec


def _fixed_snapped(trainer: Trainer, batch: tuple[torch.Tensor, ...]) -> float:
    trainer.generator.eval()
    with torch.no_grad():
        pred, _ = trainer.generator(batch[0], generator=torch.Generator().manual_seed(1))
        return losses.snapped_chamfer(pred, batch[1], *batch[3:]).item()


def test_the_snapped_objective_trains_on_scan_patches(street_patches: tuple[PatchSet, Path, DataSpec],
                                                      tmp_path: Path) -> None:
    patches, cache, spec = street_patches
    # from the pipeline's weights (a random start learns little in a few steps)
    recipe = _recipe(cache, tmp_path, data=spec, objective="snapped_chamfer", lr_generator=3e-4, alpha=1.0,
                     frame_k=24, init_weights="cadpu_r4_lidar_alpha1")
    trainer = Trainer(recipe, patches, torch.device("cpu"))
    batch = trainer.batch()
    assert len(batch) == 10  # the augmentation and the frames ride with the pairs
    before = _fixed_snapped(trainer, batch)
    for _ in range(15):  # measured: 0.964 of the start
        terms = trainer.step(batch)
    assert np.isnan(terms["emd"]) and np.isfinite(terms["snapped_chamfer"])
    assert terms["generator"] == pytest.approx(1024 * terms["snapped_chamfer"] + 0.15 * terms["regularizer"], rel=1e-4)
    assert _fixed_snapped(trainer, batch) < 0.98 * before


def test_the_snapped_objective_refuses_patches_without_frames(tiny_patches: tuple[PatchSet, Path],
                                                              tmp_path: Path) -> None:
    patches, cache = tiny_patches
    with pytest.raises(ValueError, match="snapped_chamfer needs scan patches"):
        Trainer(_recipe(cache, tmp_path, objective="snapped_chamfer"), patches, torch.device("cpu"))
    with pytest.raises(ValueError, match="objective must be one of"):
        _recipe(cache, tmp_path, objective="chamfer")


def test_a_log_begun_before_a_column_was_added_keeps_its_header(tiny_patches: tuple[PatchSet, Path],
                                                                tmp_path: Path) -> None:
    _, cache = tiny_patches
    recipe = _recipe(cache, tmp_path, steps=3, checkpoint_every=1, threads=1)
    train(recipe, progress=False, max_seconds=0.0)
    log = tmp_path / "log.csv"
    old_columns = "step,seconds,lr_g,emd,regularizer,adversarial,generator,discriminator"
    first = log.read_text().splitlines()[1].split(",")
    log.write_text(old_columns + "\n" + ",".join(first[:4] + first[5:]) + "\n")  # the row without snapped_chamfer
    train(recipe, progress=False, resume=True)
    rows = log.read_text().strip().splitlines()
    assert rows[0] == old_columns and [len(r.split(",")) for r in rows[1:]] == [8, 8, 8]


def test_azimuth_augmentation_only_turns_patches_about_the_vertical(street_patches: tuple[PatchSet, Path, DataSpec],
                                                                     tmp_path: Path) -> None:
    patches, cache, spec = street_patches
    recipe = _recipe(cache, tmp_path, data=spec, objective="snapped_chamfer", augmentation="azimuth")
    inputs, truth, _, rotations, scales, *_ = Trainer(recipe, patches, torch.device("cpu")).batch()
    torch.testing.assert_close(rotations[:, 2], torch.tensor([0.0, 0.0, 1.0]).expand(len(rotations), 3))
    assert torch.all(scales == 1)
    # heights, and distances from the vertical axis, are those of the stored pairs: no tilt, scale or jitter
    index = [int(np.flatnonzero((patches.truth[:, :, 2] == t[:, 2].numpy()).all(1))[0]) for t in truth]
    stored = torch.from_numpy(patches.inputs[index])
    torch.testing.assert_close(inputs[..., 2], stored[..., 2])
    torch.testing.assert_close(inputs[..., :2].norm(dim=-1), stored[..., :2].norm(dim=-1))
    with pytest.raises(ValueError, match="augmentation must be one of"):
        _recipe(cache, tmp_path, augmentation="tilt")


def test_the_command_says_weights_written_only_when_it_wrote_them(tiny_patches: tuple[PatchSet, Path],
                                                                   tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    # a resume at the last step leaves the file as it is, and said so, then printed "weights written
    # to ..." all the same (a training user's trial)
    import yaml

    _, cache = tiny_patches
    recipe_file = tmp_path / "recipe_in.yaml"
    recipe_file.write_text(yaml.safe_dump(dataclasses.asdict(_recipe(cache, tmp_path / "run", steps=2))))
    main([str(recipe_file)])
    assert f"weights written to {tmp_path / 'run' / 'generator.pt'}" in capsys.readouterr().out
    main([str(recipe_file), "--resume"])
    said = capsys.readouterr()
    assert "weights written" not in said.out and "is left as it is" in said.err
