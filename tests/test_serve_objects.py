"""`flextrack serve --objects DIR` (issue 35): a real server on loopback serving a BOP models folder it was
never configured for, its viewpoint models prepared into the cache by `flextrack prepare` and read
before SERVING; bad folders, meshes, objects and priors refused clearly; the guide view written."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import grpc
import numpy as np
import pytest
import trimesh

from flextrack import wire
from flextrack.formats import bop
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

REPO = Path(__file__).resolve().parent.parent
LMO = REPO.parent / "shared" / "data" / "lmo"
CAT = "obj_000006"
SCENE = LMO / "test" / "000002"
FRAME = 3  # the cat 99 % visible


def _need_lmo() -> None:
    if not (LMO / "models" / f"{CAT}.ply").is_file() or not (SCENE / "rgb" / f"{FRAME:06d}.png").is_file():
        pytest.skip(f"the shared data folder lacks LM-O ({LMO}: models and test scene 2)")


def _flextrack(*args: str, env: dict, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flextrack", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=300, check=False, **kw)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A models folder holding the LM-O cat alone, a config (pnp knows only a box; region, with a small view
    sphere to keep the test short; pnp_region chains them) and a cache folder of its own (FLEXTRACK_CACHE)."""
    _need_lmo()
    root = tmp_path_factory.mktemp("serve_objects")
    models = root / "models"
    models.mkdir()
    shutil.copy(LMO / "models" / f"{CAT}.ply", models)
    info = bop.read_models_info(LMO / "models" / "models_info.json")
    bop.write_models_info(models / "models_info.json", {6: info[6]})
    trimesh.creation.box(extents=(80.0, 60.0, 40.0)).export(root / "box.ply")
    config = root / "server.toml"
    config.write_text(textwrap.dedent("""
        [objects.box]
        model = "box.ply"
        [[estimators]]
        name = "pnp"
        kind = "pnp"
        objects = ["box"]
        [[estimators]]
        name = "region"
        kind = "region"
        objects = ["box"]
        [estimators.params]
        views_subdivisions = 2
        [[estimators]]
        name = "pnp_region"
        kind = "chained"
        [estimators.params]
        global = "pnp"
        local = "region"
    """))
    env = {**os.environ, "FLEXTRACK_CACHE": str(root / "cache")}
    return root, models, config, env


@pytest.fixture(scope="module")
def server(setup):
    """`flextrack prepare` fills the cache, then `flextrack serve --objects` reads it before SERVING."""
    root, models, config, env = setup
    done = _flextrack("prepare", "--config", str(config), "--objects", str(models), env=env)
    assert done.returncode == 0, done.stderr
    assert f"region {CAT}" in " ".join(done.stdout.split()) and "1 built" in done.stdout
    cached = sorted((root / "cache" / "region").glob("viewpoints_*.npz"))
    assert len(cached) == 1
    proc = subprocess.Popen([sys.executable, "-m", "flextrack", "serve", "--port", "0", "--config", str(config),
                             "--objects", str(models)], cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    try:
        records = [json.loads(proc.stderr.readline()) for _ in range(3)]
        assert [r["msg"] for r in records] == ["listening", "viewpoint models ready", "serving"], records
        ready = records[1]
        assert ready["objects"] == [CAT] and ready["built"] == 0 and ready["from_cache"] == 1  # prepared: no build
        assert sorted((root / "cache" / "region").glob("viewpoints_*.npz")) == cached
        with grpc.insecure_channel(records[0]["address"]) as channel:
            yield pb_grpc.PoseEstimationStub(channel)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _frame() -> tuple[bytes, PinholeCamera, np.ndarray]:
    K = bop.read_scene_camera(SCENE / "scene_camera.json")[FRAME]
    T = bop.read_scene_gt(SCENE / "scene_gt.json", 6)[FRAME]
    return (SCENE / "rgb" / f"{FRAME:06d}.png").read_bytes(), PinholeCamera.from_K(K, 640, 480), T


def _request(estimator: str, object_id: str = CAT, prior: pb.PosePrior | None = None) -> pb.EstimateRequest:
    png, camera, _ = _frame()
    return pb.EstimateRequest(session_id="s", frame_id=FRAME, estimator=estimator, object_id=object_id, prior=prior,
                              image=pb.Image(encoding=pb.Image.PNG, data=png, width=640, height=480),
                              intrinsics=wire.intrinsics_to_pb(camera))


def test_list_estimators_names_the_folders_objects(server):
    listed = {e.name: list(e.objects) for e in server.ListEstimators(pb.ListEstimatorsRequest(), timeout=30).estimators}
    assert listed == {"pnp": ["box"], "region": ["box", CAT], "pnp_region": ["box", CAT]}


def test_region_refines_a_prior_on_a_real_frame_of_the_served_object(server):
    _, camera, T = _frame()
    vertices = trimesh.load(LMO / "models" / f"{CAT}.ply", process=False).vertices / 1000.0
    T_prior = se3.make(so3.exp(np.radians([4.0, -3.0, 3.0])) @ T[:3, :3], T[:3, 3] + [0.018, -0.012, 0.01])
    prior = pb.PosePrior(pose=wire.pose_to_pb(T_prior), covariance=wire.covariance_to_pb(
        wire.diagonal_covariance(np.radians(5.0), 0.01)))
    for estimator in ("region", "pnp_region"):  # the chain asks its local part: pnp does not know the cat
        answer = server.Estimate(_request(estimator, prior=prior), timeout=60)
        assert answer.status == pb.EstimateResponse.OK, answer.message
        assert "local" in answer.stage_ms or estimator == "region"
        error_px = metrics.proj_px(wire.pose_from_pb(answer.pose), T, camera, vertices)
        prior_px = metrics.proj_px(T_prior, T, camera, vertices)
        assert error_px < min(5.0, 0.5 * prior_px), (error_px, prior_px)


def test_bad_requests_are_refused_with_their_reason(server):
    _, _, T = _frame()
    with pytest.raises(grpc.RpcError) as err:  # the chain's global part does not know the cat: no prior, no answer
        server.Estimate(_request("pnp_region"), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "only from a prior" in err.value.details()
    with pytest.raises(grpc.RpcError) as err:
        server.Estimate(_request("region", "obj_000042", pb.PosePrior(pose=wire.pose_to_pb(T))), timeout=30)
    assert err.value.code() == grpc.StatusCode.NOT_FOUND and "obj_000042" in err.value.details()
    with pytest.raises(grpc.RpcError) as err:
        server.Estimate(_request("pnp_region", "obj_000042"), timeout=30)
    assert err.value.code() == grpc.StatusCode.NOT_FOUND and "obj_000042" in err.value.details()
    pose = wire.pose_to_pb(T)
    pose.qw *= 1.7  # a scaled rotation: not a rigid transform
    with pytest.raises(grpc.RpcError) as err:
        server.Estimate(_request("region", prior=pb.PosePrior(pose=pose)), timeout=30)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "rigid" in err.value.details()


@pytest.mark.parametrize("command", ["serve", "prepare"])
def test_a_bad_folder_or_mesh_is_one_line_and_exit_2_and_nothing_is_written(setup, tmp_path, command):
    _, models, config, env = setup
    env = {**env, "FLEXTRACK_CACHE": str(tmp_path / "cache")}
    empty = tmp_path / "empty"
    empty.mkdir()
    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(models / "models_info.json", broken)
    (broken / f"{CAT}.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nthis is no mesh\n")
    unlisted = tmp_path / "unlisted"
    shutil.copytree(models, unlisted)
    shutil.copy(unlisted / f"{CAT}.ply", unlisted / "obj_000007.ply")
    cases = [(empty, "no BOP models"), (tmp_path / "nowhere", "not a folder"), (broken, "does not load as a mesh"),
             (unlisted, "not listed")]
    port = ["--port", "0"] if command == "serve" else []
    for folder, why in cases:
        done = _flextrack(command, *port, "--config", str(config), "--objects", str(models), "--objects", str(folder),
                          env=env)
        assert done.returncode == 2, (folder, done.stderr)
        assert len(done.stderr.splitlines()) == 1 and why in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not (tmp_path / "cache").exists()  # nothing was built for a command line that was refused


def test_guide_view_writes_the_outline_and_the_pose_it_stands_for(tmp_path):
    _need_lmo()
    from flextrack.cli import main

    mesh = LMO / "models" / f"{CAT}.ply"
    out = tmp_path / "guide.png"
    assert main(["guide-view", "--object", str(mesh), "--out", str(out)]) == 0
    rgba = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == (480, 640, 4)
    doc = json.loads(out.with_suffix(".json").read_text())
    T = np.array(doc["T_CO"])
    np.testing.assert_allclose(wire.pose_from_pb(pb.Pose(**doc["pose"])), T, atol=1e-6)
    camera = PinholeCamera(**{k: v for k, v in doc["intrinsics"].items() if k != "distortion"})
    assert (camera.width, camera.height) == (640, 480)
    # the drawn object is where its pose projects it: the mask's box is the projected vertices' box
    vertices = trimesh.load(mesh, process=False).vertices / 1000.0
    uv = camera.project(se3.transform_points(T, vertices))
    ys, xs = np.nonzero(rgba[..., 3])
    np.testing.assert_allclose([xs.min(), ys.min(), xs.max(), ys.max()],
                               [*uv.min(axis=0), *uv.max(axis=0)], atol=4.0)  # the outline is 3 px wide
    diameter_px = max(np.ptp(uv, axis=0))
    assert 0.3 * 480 < diameter_px < 0.6 * 480  # a working distance: about half the image, all of it in view
    assert rgba[..., 3].max() == 255 and 0 < (rgba[..., 3] == 255).sum() < (rgba[..., 3] > 0).sum()


def test_guide_view_refuses_bad_arguments_in_one_line(tmp_path, capsys):
    from flextrack.cli import main

    for args, why in [(["--object", str(tmp_path / "no.ply")], "no such file"),
                      (["--object", __file__, "--fill", "2"], "--fill"),
                      (["--object", __file__, "--elevation-deg", "90"], "--elevation-deg")]:
        assert main(["guide-view", *args, "--out", str(tmp_path / "g.png")]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and why in err, err
    assert not (tmp_path / "g.png").exists()


def test_track_serves_the_folders_objects_from_its_embedded_server(setup, tmp_path, monkeypatch, capsys):
    from flextrack.cli import main
    from flextrack.runners import session
    from flextrack.testing.toy_sequence import write_orbit_sequence

    _, models, config, env = setup
    monkeypatch.setenv("FLEXTRACK_CACHE", env["FLEXTRACK_CACHE"])
    seq = write_orbit_sequence(tmp_path / "orbit", frames=5)
    registry = session.registry_for(seq, session.RunSpec(backend="pnp_region", config=config, objects=(models,)))
    assert registry.get("pnp_region").objects == ["box", CAT]
    out = ["--out", str(tmp_path / "o")]
    for args, why in [(["--config", str(config), "--backend", "pnp_region", "--objects", str(tmp_path)], "no BOP models"),
                      (["--server", "127.0.0.1:1", "--backend", "pnp_region", "--objects", str(models)],
                       "flextrack serve --objects"),
                      (["--backend", "gt", "--objects", str(models)], "is an oracle")]:
        assert main(["track", str(seq.root), *args, *out]) == 2
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and why in err, err


def test_prepare_without_objects_prepares_the_configs_region_objects(setup, tmp_path):
    _, _, config, env = setup
    env = {**env, "FLEXTRACK_CACHE": str(tmp_path / "cache")}
    done = _flextrack("prepare", "--config", str(config), env=env)
    assert done.returncode == 0 and "region box" in " ".join(done.stdout.split()), done.stderr
    assert len(list((tmp_path / "cache" / "region").glob("viewpoints_*.npz"))) == 1
    bare = tmp_path / "bare.toml"
    bare.write_text('[[estimators]]\nname = "gt"\nkind = "gt_oracle"\n')
    done = _flextrack("prepare", "--config", str(bare), env=env)
    assert done.returncode == 2 and "declares no region estimator" in done.stderr
