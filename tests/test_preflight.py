"""Preflight: one clear line and a non-zero exit, before anything expensive runs."""

import numpy as np
import pytest

from acoustlab.core.errors import ConfigError, DataError
from acoustlab.run.preflight import check_argv
from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config


def test_missing_site_names_the_fix():
    with pytest.raises(ConfigError, match=r"\+site=NAME.*forest.*frozen_lake"):
        check_argv(["model=xgboost"])


def test_site_without_plus_is_explained():
    with pytest.raises(ConfigError, match=r"\+site=forest"):
        check_argv(["site=forest"])


@pytest.mark.parametrize("arg,group", [("model=catboost", "model"), ("+site=marsh", "site"), ("gate=foo,bounding_box", "gate")])
def test_unknown_option_lists_the_available_ones(arg, group):
    with pytest.raises(ConfigError, match=rf"unknown option .* for {group}; available: "):
        check_argv(["+site=forest", arg] if "site" not in arg else [arg])


def test_help_and_sweeps_pass():
    check_argv(["--help"])
    check_argv(["-m", "+site=frozen_lake,forest", "model=xgboost,random_forest"])


@pytest.mark.slow
def test_cli_without_site_fails_in_one_line(run_cli):
    proc = run_cli("model=xgboost")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and "+site=" in lines[0] and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_cli_unknown_option_fails_in_one_line(run_cli):
    proc = run_cli("+site=frozen_lake", "model=nope")
    assert proc.returncode == 2
    from acoustlab.run.registry import group_options

    assert proc.stderr.strip().count("\n") == 0 and f"available: {', '.join(group_options('model'))}" in proc.stderr


def _site(compose_cfg, *overrides):
    return site_from_config(compose_cfg(["+site=frozen_lake", *overrides]).site)


def test_fewer_than_three_mics(compose_cfg):
    with pytest.raises(ConfigError, match="2 microphones.*at least 3"):
        _site(compose_cfg, "site.mics=[[0,0,1],[10,0,1]]")


def test_collinear_mics(compose_cfg):
    with pytest.raises(ConfigError, match="collinear"):
        _site(compose_cfg, "site.mics=[[0,0,1],[10,0,1],[20,0,1]]")


def test_empty_noise_pool(compose_cfg):
    with pytest.raises(ConfigError, match="noise.regimes is empty"):
        _site(compose_cfg, "site.noise.regimes=[]")


def test_empty_species_pool(compose_cfg):
    with pytest.raises(ConfigError, match="species_pool is empty"):
        _site(compose_cfg, "site.species_pool=[]")


@pytest.mark.parametrize("simulator", ["free_field", "outdoor"])
def test_non_positive_sample_rate(compose_cfg, simulator):
    cfg = compose_cfg(["+site=frozen_lake", f"simulator={simulator}", "simulator.sample_rate_hz=0"])
    with pytest.raises(ConfigError, match="sample_rate_hz must be positive"):
        build(cfg.simulator, "simulator")


def test_sample_rate_below_the_call_band(compose_cfg):
    cfg = compose_cfg(["+site=frozen_lake", "simulator.sample_rate_hz=6000"])
    with pytest.raises(ConfigError, match="below twice"):
        build(cfg.simulator, "simulator")


def test_empty_call_pool(compose_cfg):
    cfg = compose_cfg(["+site=frozen_lake", "simulator=free_field", "simulator.calls=[]"])
    with pytest.raises(ConfigError, match="call pool"):
        build(cfg.simulator, "simulator")
    # only share-alike species, without opting in to them
    cfg = compose_cfg(["+site=frozen_lake", "site.species_pool=[bewicks_wren]"])
    with pytest.raises(ConfigError, match="call pool .* is empty .*include_share_alike"):
        build(cfg.simulator, "simulator").validate(site_from_config(cfg.site))
    cfg = compose_cfg(["+site=frozen_lake", "site.species_pool=[dodo]"])
    with pytest.raises(ConfigError, match="unknown species \\['dodo'\\]"):
        build(cfg.simulator, "simulator").validate(site_from_config(cfg.site))


def test_recording_too_short_for_the_site(compose_cfg):
    cfg = compose_cfg(["+site=forest", "simulator.duration_s=0.2"])
    sim = build(cfg.simulator, "simulator")
    with pytest.raises(ConfigError, match="duration_s=0.2 s is too short"):
        sim.validate(site_from_config(cfg.site))


def test_bad_mics_csv_names_file_and_column(tmp_path, compose_cfg):
    bad = tmp_path / "mics.csv"
    bad.write_text("x_m,y_m\n0,0\n10,0\n0,10\n")
    with pytest.raises(DataError, match=r"mics.csv lacks columns \['z_m'\]"):
        _site(compose_cfg, f"site.mics_csv={bad}")
    bad.write_text("x_m,y_m,z_m\n0,0,1\n10,abc,1\n0,10,1\n")
    with pytest.raises(DataError, match=r"row 3 column 'y_m' is not a finite number"):
        _site(compose_cfg, f"site.mics_csv={bad}")
    with pytest.raises(DataError, match="does not exist"):
        _site(compose_cfg, f"site.mics_csv={tmp_path / 'missing.csv'}")


def test_site_from_csv_files(tmp_path, compose_cfg):
    mics = tmp_path / "m.csv"
    mics.write_text("mic_id,x_m,y_m,z_m\na,0,0,1.5\nb,30,0,1.5\nc,15,25,1.5\nd,15,8,2\n")
    trees = tmp_path / "t.csv"
    trees.write_text("x_m,y_m,diameter_m\n5,5,0.3\n20,10,0.45\n")
    site = site_from_config(compose_cfg(["+site=from_csv", "site.name=mine", f"site.mics_csv={mics}", f"site.trees_csv={trees}"]).site)
    assert site.n_mics == 4 and site.tree_positions_m.shape == (2, 2)
    np.testing.assert_allclose(site.trunk_diameters_m, [0.3, 0.45])


def test_unreadable_noise_recording_names_the_file(tmp_path, compose_cfg):
    from acoustlab.toolkit.audio import load_mono

    bad = tmp_path / "broken.flac"
    bad.write_bytes(b"not audio at all")
    with pytest.raises(DataError, match="cannot read audio file .*broken.flac"):
        load_mono(str(bad), 24000.0)
    cfg = compose_cfg(["+site=frozen_lake", f"site.noise.regimes=[{{kind: recorded, files: [{tmp_path / 'absent.flac'}]}}]"])
    with pytest.raises(DataError, match="absent.flac does not exist"):
        site_from_config(cfg.site)


def test_sweep_jobs_follow_hydra_a_command_line_key_replaces_the_sweep_params():
    from omegaconf import OmegaConf

    from acoustlab.run.sweep import sweep_jobs

    cfg = OmegaConf.create(
        {
            "hydra": {
                "sweeper": {"params": {"gate": "solver_only,model_only,hybrid", "features.drop": "[],[tdoa]"}},
                "overrides": {"task": ["+site=forest", "gate=learned", "model=xgboost,knn"]},
            }
        }
    )
    jobs = sweep_jobs(cfg)
    assert len(jobs) == 4  # 2 drops × 1 gate (the command line's) × 2 models, not 2 × 3 × 2
    assert all("gate=learned" in job for job in jobs)


@pytest.mark.slow
def test_a_mistyped_key_gets_the_closest_existing_one(run_cli, compose_cfg):
    """Typed nodes are checked before Hydra composes; plugin settings when the plugin is built; both say "did you mean"."""
    from acoustlab.run.preflight import check_argv
    from acoustlab.run.registry import build

    with pytest.raises(ConfigError, match=r"data.n_event: data has no key 'n_event'; did you mean data.n_events\?"):
        check_argv(["+site=frozen_lake", "data.n_event=5"])
    with pytest.raises(ConfigError, match=r"did you mean pipeline.trust.handover_check\?"):
        check_argv(["+site=frozen_lake", "pipeline.trust.handover_chek=false"])
    check_argv(["+site=frozen_lake", "protocol.test_fraction=0.2", "conformal.scorers.fixed.n_bins=2"])  # plugin nodes are free-form
    cfg = compose_cfg(["+site=frozen_lake", "+protocol.test_fractoin=0.2"])
    with pytest.raises(ConfigError, match=r"protocol.test_fractoin is not a setting of SimOnlyProtocol; did you mean test_fraction\?"):
        build(cfg.protocol, "protocol")


@pytest.mark.parametrize("value", ["/data/Gärten/audio", "/data/it's", "/data/[x]"])
def test_a_setting_hydra_cannot_read_says_how_to_quote_it(value):
    """Hydra's lexer stops on letters beyond ASCII, a quote or a bracket with no word of which setting: one line naming
    it, with its quoted form, which then reads."""
    with pytest.raises(ConfigError, match="cannot read the setting .field.audio_dir=.*only in double quotes, as ") as caught:
        check_argv(["+site=frozen_lake", f"field.audio_dir={value}"])
    quoted = str(caught.value).split("only in double quotes, as ", 1)[1].rsplit(" (the whole setting", 1)[0]
    assert quoted == f'field.audio_dir="{value}"'
    check_argv(["+site=frozen_lake", quoted])
    check_argv(["+site=frozen_lake", "field.audio_dir=/data/my marsh"])  # spaces read as they are
