"""``indoorbev-sim`` argument checks that need no simulated frames."""

import pytest
from indoorbev_sim.cli import main


@pytest.mark.parametrize(
    "flag, value", [("--batch", "0"), ("--batch", "-1"), ("--frames", "0"), ("--frames", "-3")]
)
def test_check_needs_positive_frames_and_batch(flag, value, capsys):
    with pytest.raises(SystemExit) as e:
        main(["check", "--preset", "tiny", "--cache", "", flag, value])
    assert e.value.code == 2
    assert f"argument {flag}: must be > 0, got {value}" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-2", "nan", "inf"])
def test_publish_needs_a_positive_rate(value, capsys):
    with pytest.raises(SystemExit) as e:
        main(["ros2", "publish", "--rate", value])
    assert e.value.code == 2
    assert f"argument --rate: must be a finite number > 0, got {value}" in capsys.readouterr().err


@pytest.mark.parametrize("frames, batch", [(0, 4), (8, 0), (-1, 4), (8, 2.0)])
def test_check_library_needs_positive_frames_and_batch(frames, batch):
    from indoorbev_sim.labels import check

    from indoorbev_jax.config import Config

    with pytest.raises(ValueError, match="(frames|batch_size): expected a whole number > 0"):
        check(Config.tiny(), frames, batch, seed=0)


@pytest.mark.parametrize("seed", [-1, 2**32, 1.5])
def test_check_library_and_cli_need_a_32_bit_seed(seed, capsys):
    """jax.random.key folds a seed into 32 bits: others would repeat seeds in [0, 2**32)."""
    from indoorbev_sim.labels import check

    from indoorbev_jax.config import Config

    with pytest.raises(ValueError, match=r"seed: expected a whole number in \[0, 2\*\*32\)"):
        check(Config.tiny(), 8, 4, seed=seed)
    with pytest.raises(SystemExit) as e:
        main(["check", "--preset", "tiny", "--seed", str(seed)])
    assert e.value.code == 2
    assert "argument --seed: expected a whole number in [0, 2**32)" in capsys.readouterr().err
