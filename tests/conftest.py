"""Shared test set-up: DDS stays on this machine, in a domain of this test run's own."""
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("ROS_DOMAIN_ID", str(os.getpid() % 90 + 5))

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"


def installed_executable(name: str) -> Path:
    """Where `ros2 run inseggan_ros <name>` finds the executable:
    <prefix>/lib/inseggan_ros/<name>."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    try:
        prefix = get_package_prefix("inseggan_ros")
    except PackageNotFoundError:
        pytest.fail("inseggan_ros is not on AMENT_PREFIX_PATH: build it with colcon and "
                    "`source install/setup.bash` (make test does both)")
    return Path(prefix) / "lib" / "inseggan_ros" / name


def checkpoint_without_settings(path: Path) -> Path:
    """The shipped cylinder model without its stored settings, as a training checkpoint has
    none, written to `path`."""
    from inseggan_ros.core import checkpoint

    state = checkpoint.load(REPO / "models" / "cylinder" / "model.pt")
    del state["inference"]
    return checkpoint.save(path, state)


def run_cli(*args, timeout=300, check=False) -> subprocess.CompletedProcess:
    """Run the installed `inseggan` command."""
    proc = subprocess.run([str(installed_executable("inseggan")), *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    if check and proc.returncode != 0:
        raise AssertionError(f"inseggan {args} failed ({proc.returncode}):\n{proc.stderr}")
    return proc


def refused(*args) -> subprocess.CompletedProcess:
    """`inseggan ARGS` run in this process, for a command expected to refuse its input:
    the same parser, checks and one-line errors (`cli.app.main`) as the installed command,
    without a new interpreter's start-up (about 3 s of imports a call, most of a refusal's
    time). The commands that must work run through `run_cli`."""
    import contextlib
    import io

    from inseggan_ros.cli.app import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in args])
        except SystemExit as e:  # argparse's errors
            rc = e.code if isinstance(e.code, int) else int(e.code is not None)
    return subprocess.CompletedProcess(["inseggan", *map(str, args)], rc, out.getvalue(),
                                       err.getvalue())


def _param_client(*args) -> str:
    p = subprocess.run([sys.executable, str(Path(__file__).parent / "param_client.py"),
                        *map(str, args)], capture_output=True, text=True, timeout=90)
    return p.stdout.strip()


def set_param(node: str, name: str, value: str) -> str:
    """Set a running node's parameter from another process (value: a Python literal)
    -> 'ok' or 'rejected: <reason>'."""
    return _param_client("set", node, name, value)


def set_params(node: str, *pairs: tuple[str, str]) -> list[str]:
    """`set_param` for each (name, value) in turn, one request each, from one process (a
    process per set costs a second or two of start-up and discovery) -> a result per pair."""
    return _param_client("set", node, *(v for pair in pairs for v in pair)).splitlines()


def get_params(node: str, *names: str) -> dict:
    """A running node's parameters, read from another process."""
    import json

    return json.loads(_param_client("get", node, *names))


@pytest.fixture
def tmp(tmp_path):
    return tmp_path


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory):
    """A tiny model as `inseggan train` leaves it (learned renderer, 10 iterations) and the
    simulated data set it was trained on: root/run/best.pt, root/data."""
    root = tmp_path_factory.mktemp("seg")
    run_cli("simulate", "--quiet", "--count", "40", "--split", "0.5,0.25,0.25", "--out",
            root / "data", check=True)
    run_cli("train", "--data", root / "data", "--out", root / "run", "--iterations", "10",
            "--eval-every", "10", "--config", "cpu", "--nf", "8", "--batch-size", "4",
            "--quiet", "--device", "cpu", check=True, timeout=600)
    return root


@pytest.fixture(scope="module")
def cylinder_bag():
    """The shipped cylinder model (one torch thread) and its labelled sample bag's frames; one
    per test module, which may change the model's settings."""
    import torch

    from inseggan_ros.data import datasets as data
    from inseggan_ros.runtime.segment import Segmenter

    torch.set_num_threads(1)
    seg = Segmenter.from_checkpoint(REPO / "models" / "cylinder" / "model.pt", device="cpu")
    seg.inference = zbuffer_settings(seg.inference)
    return seg, data.load_bag(BAGS / "cylinder_sim", seg.prep_cfg)


def zbuffer_settings(cfg):
    """realtime.yaml over a model's settings, with the z-buffer's labels (`centre_votes: off`):
    what the shipped cylinder ran before its centre votes, for the tests of what comes after
    the z-buffer (tau, the vote, the split; over centre votes there is no vote, and one
    starting point: their own tests are test_centres.py)."""
    from inseggan_ros.core import settings

    return replace(settings.apply_file(cfg, "realtime"), centre_votes="off")


@pytest.fixture(scope="session")
def python():
    return sys.executable


def which(name):
    return shutil.which(name)


# The test files that train or simulate the most, longest first (their tests' summed time in a
# full run): collected before the others so that, when pytest-xdist shares the files between
# processes (scripts/test.sh, whose --no-loadscope-reorder keeps this order), none of them
# starts last and leaves the other process idle.
LONGEST_FIRST = ("test_loop.py", "test_distill.py", "test_models.py", "test_pilematch.py",
                 "test_train.py", "test_centres.py", "test_cli.py", "test_shapefit.py",
                 "test_family.py", "test_unlabelled.py", "test_selffit.py", "test_label_head.py",
                 "test_sizing.py", "test_dataset.py", "test_bags.py", "test_template.py")


# The tests that took about four seconds or more in a run of the fast tier (training,
# simulation, a whole loop, several CLI processes, a node replaying a bag): marked `slow`, so
# that the fast tier (`make test-fast`, `-m "not slow"`) runs in under 3 minutes on 2 cores
# for every change; `make test` (CI) runs them all. An entry names a test (every case of it)
# or one case of a parametrized test ("name[case]"); the fast tier keeps a quicker case of each.
SLOW = {
    "test_loop.py": (
        "test_a_tiny_loop_explains_held_out_scenes_of_its_shape_better_than_its_starting_point",
        "test_one_command_from_a_bag_learns_the_shape_then_ships_a_model",
        "test_the_loop_piles_a_nut_with_its_hole_where_the_grid_asks_for_one",
        "test_the_loop_piles_a_disc_template_matched_to_the_frames_and_keeps_the_rod",
        "test_the_loop_fits_a_convex_template_from_the_rod_and_piles_and_ships_it",
        "test_the_default_loop_chooses_the_template_family_then_piles_it_once",
        "test_loop_refuses_a_missing_model_and_frames_of_another_camera",
    ),
    "test_family.py": (
        "test_a_scale_at_which_the_bin_cannot_hold_n_parts_is_no_candidate_s_end",
        "test_a_block_s_frames_choose_a_box_over_the_rod_and_the_taper_and_resume",
    ),
    "test_train.py": (
        "test_tiny_training_run_improves_reconstruction",
        "test_killed_run_resumes_from_its_last_checkpoint",
        "test_ddp_two_processes_gloo_identical_weights",
        "test_n_is_the_data_sets_parts_per_bin_unless_given",
        "test_best_checkpoint_is_the_best_validation_even_the_starting_point",
    ),
    "test_centres.py": (
        "test_self_labels_teach_the_net_the_models_own_labels_of_the_users_frames",
        "test_self_labels_from_a_recording_label_all_its_frames",
        "test_a_short_training_run_segments_held_out_piles_better_and_ships_in_the_model",
    ),
    "test_label_head.py": (
        "test_a_short_training_run_explains_held_out_scenes_better_and_ships_in_the_model",
    ),
    "test_distill.py": (
        "test_the_users_own_frames_are_reconstructed_better_with_their_loss",
        "test_a_wider_encoder_widened_from_the_source_trains_and_segments",
        "test_distillation_brings_the_encoder_towards_its_refined_poses",
        "test_a_narrower_encoder_pruned_from_the_source_learns_the_refined_poses",
        "test_distill_refuses_a_learned_renderer_and_a_missing_checkpoint",
    ),
    "test_pilematch.py": (
        "test_a_recording_s_piles_are_seen_through_the_camera_its_frames_give",
        "test_piles_choose_the_head_the_frames_were_made_of_and_a_search_resumes",
        "test_a_uniform_rod_gets_the_flange_its_frames_were_made_of",
        "test_the_card_draws_the_piles_template_beside_the_models_own",
        "test_a_nut_s_piles_choose_a_ring_with_its_hole_over_a_solid_disc",
        "test_a_cone_s_piles_choose_a_frustum_with_its_taper_over_a_straight_disc",
    ),
    "test_models.py": (
        "test_segments_its_sample_bag_as_its_card_says[bolt]",
        "test_segments_its_sample_bag_as_its_card_says[bolt_tilted]",
        "test_segments_its_sample_bag_as_its_card_says[cone_tilted]",
        "test_segments_its_sample_bag_as_its_card_says[hex_nut_tilted]",
        "test_segments_its_sample_bag_as_its_card_says[pin_connector_tilted]",
        "test_segments_its_sample_bag_as_its_card_says[stopper_tilted]",
        "test_segments_its_sample_bag_as_its_card_says[wooden_block_tilted]",
        "test_card_run_records_another_training_run_on_the_cards_test_split",
        "test_card_shape_adds_the_learned_template_against_the_true_part",
        "test_card_settings_ships_other_settings_and_measures_the_card_anew",
        "test_quality_settings_segment_the_default_models_bag_better_than_kmeans",
    ),
    "test_template.py": (
        "test_shape_fidelity_of_known_bodies",
        "test_a_rod_of_spheres_as_pieces_holds_the_spheres_and_little_else",
        "test_exact_height_map_matches_ray_casting",
        "test_short_training_run_moves_a_box_template_towards_the_true_block",
    ),
    "test_picks.py": (
        "test_picks_over_dds_match_the_simulator",
        "test_without_a_matching_camera_info_labels_go_on_and_diagnostics_say_why",
        "test_camera_info_is_taken_beside_a_remapped_depth_topic",
    ),
    "test_segmenter.py": (
        "test_tilted_realsense_recording_is_segmented_end_to_end",
        "test_quality_file_keeps_the_models_own_vote_and_a_training_checkpoint_runs_realtime",
        "test_replayed_bag_is_segmented_with_headers_masks_and_diagnostics",
        "test_shipped_parameter_files_set_the_segmenter",
        "test_an_incompatible_model_file_stops_the_node",
        "test_bad_frames_are_counted_and_skipped_and_the_node_keeps_serving",
        "test_replayed_bag_is_segmented_better_than_kmeans",
    ),
    "test_launch.py": (
        "test_parameters_the_launch_files_set_are_declared_by_the_nodes",
    ),
    "test_dds.py": (
        "test_large_frames_arrive_between_processes_with_the_profile",
    ),
    "test_bin_replay.py": (
        "test_simulated_frames_as_compressed_depth",
        "test_large_frames_arrive_with_only_what_ros2_run_sets_up",
        "test_bag_frames_arrive_with_their_stamps[hex_nut_sim_32fc1]",
        "test_compressed_bag_replays_as_raw_images[hex_nut_sim_32fc1]",
        "test_compressed_bag_replayed_as_compressed_depth_passes_its_bytes",
        "test_simulated_frames_arrive_over_dds",
    ),
    "test_selffit.py": (
        "test_self_fit_teaches_the_encoder_its_slow_labels_and_the_card_says_so",
    ),
    "test_shapefit.py": (
        "test_a_killed_fit_resumes_where_it_stopped_and_ends_as_an_unbroken_one",
        "test_a_short_fit_moves_the_box_towards_the_true_block_and_is_not_redone",
        "test_shape_fit_with_no_iterations_writes_the_discs_a_simulator_drops",
    ),
    "test_sizing.py": (
        "test_the_loop_sizes_the_rod_then_chooses_its_scale_and_resumes",
    ),
    "test_segment_eval.py": (
        "test_eval_cli_writes_table_json_and_png",
        "test_segmenter_on_a_full_resolution_frame",
    ),
    "test_unlabelled.py": (
        "test_label_free_export_of_a_data_set",
        "test_export_with_a_labels_topic_adds_miou",
        "test_check_writes_a_sheet_and_prints_the_measures",
        "test_a_model_trained_on_a_bag_records_where_its_template_is_in_metres",
        "test_unlabelled_export_writes_a_model_that_segments",
    ),
    "test_segmenter_cell.py": (
        "test_the_bin_check_warns_on_another_part_and_not_on_the_models_own",
        "test_lifecycle_is_driven_from_another_process",
        "test_enable_pauses_and_segment_next_segments_one_frame_while_paused",
        "test_picks_in_the_robot_frame_match_the_camera_picks_moved_independently",
        "test_an_empty_bin_gives_no_instance_and_the_diagnostics_say_so",
    ),
    "test_dataset.py": (
        "test_one_worker_and_two_workers_make_the_same_data_set",
        "test_contact_sheet_png",
        "test_simulate_splits_shards_and_bags",
        "test_bench_sim_prints_throughput",
        "test_existing_output_and_bad_arguments",
    ),
    "test_compressed_depth.py": (
        "test_cli_bag_info_and_check_on_a_compressed_bag",
    ),
    "test_cli.py": (
        "test_a_printed_recipe_read_back_resolves_the_same_and_flags_override_it",
        "test_loop_help_shows_the_users_options_and_the_advanced_help_the_research_ones",
        "test_ship_refuses_a_folder_without_a_model_or_a_recipe_and_a_bad_name",
        "test_ship_puts_a_runs_model_and_recipe_in_place_whole_and_only_once",
    ),
    "test_bags.py": (
        "test_cli_simulate_bag_is_atomic",
        "test_cli_simulate_bag_in_another_cell",
        "test_camera_info_recorded_after_its_image[sqlite3]",
        "test_cli_shows_the_warning_once",
        "test_bin_replay_node_replays_a_cut_bag_and_warns_once",
        "test_cli_errors_are_one_line_without_traceback",
    ),
    "test_budget.py": (
        "test_the_centre_stage_takes_the_iterations_its_share_holds_and_keeps_them_on_resume",
        "test_the_family_makes_its_first_candidate_and_no_more_once_its_share_is_spent",
    ),
    "test_model.py": (
        "test_a_bfloat16_centre_net_gives_the_float32_labels",
    ),
    "test_user_camera.py": (
        "test_simulate_camera_from_a_bag",
    ),
    "test_counts_sim.py": (
        "test_simulate_draws_a_count_per_scene_from_the_command_line",
    ),
}


@pytest.hookimpl(tryfirst=True)  # before -m deselects by the markers added here
def pytest_collection_modifyitems(config, items):
    for item in items:
        slow = SLOW.get(item.path.name, ())
        if item.originalname in slow or item.name in slow:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept
