"""`torchvol sweep` end to end on a tiny scene: CSV, contact sheet, plots."""

import csv
import math

from PIL import Image

from torchvol.cli import main
from torchvol.sweep import reference_overrides, split_values


def test_sweep_end_to_end(tmp_path, capsys):
    out = tmp_path / "sweep"
    code = main(["sweep", "cloud-puff", "--param", "march.steps=4,8", "--param", "volumes[0].sigma_t=5,10",
                 "--set", "image.width=16", "--set", "image.height=12", "--set", "lights[0].shadow.steps=2",
                 "--out", str(out)])
    assert code == 0
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert len(rows) == 4
    assert set(rows[0]) == {"march.steps", "volumes[0].sigma_t", "time_s", "density_evals", "rmse", "psnr"}
    for r in rows:
        assert float(r["time_s"]) > 0 and int(r["density_evals"]) > 0
        assert float(r["rmse"]) > 0 and math.isfinite(float(r["psnr"]))
    # more steps, closer to the reference
    err = {(r["march.steps"], r["volumes[0].sigma_t"]): float(r["rmse"]) for r in rows}
    assert err[("8", "10")] < err[("4", "10")]
    sheet = Image.open(out / "contact_sheet.png")
    assert sheet.size[0] >= 2 * 160
    assert (out / "plot_march.steps.png").is_file() and (out / "plot_volumes_0_.sigma_t.png").is_file()


def test_sweep_errors(tmp_path, capsys):
    assert main(["sweep", "cloud-puff", "--param", "march.stepz=4,8", "--out", str(tmp_path)]) == 2
    assert "did you mean 'steps'" in capsys.readouterr().err
    assert main(["sweep", "cloud-puff", "--param", "march.steps", "--out", str(tmp_path)]) == 2


def test_value_splitting_and_reference():
    assert split_values("8,16,[1,2,3],{a=1,b=2}") == ["8", "16", "[1,2,3]", "{a=1,b=2}"]
    assert reference_overrides({"march": {"steps": 8, "integrator": "alpha", "max_distance": 9}}) == {
        "integrator": "alpha", "max_distance": 9, "quality": "reference"}
