"""One batch, prepared once (`renderer.prepare`): input is refused at the boundary, before
anything renders; `render` takes a prepared `Batch` as it is; the dataset levels and keys each
scene once and takes its volume labels from the render's own context."""

import pytest

import torchvol as tv
from torchvol.renderer import executor, prepare
from torchvol.schema.batch import structure_key


def box(**image):
    return {"image": {"width": 6, "height": 4, **image}, "volumes": [{"density": {"constant": 1.0}}],
            "lights": [{"kind": "sun", "direction": [0, 1, 0]}]}


def test_a_prepared_batch_carries_its_levelled_scenes_and_structure_key():
    batch = prepare.prepare([box(), box()])
    assert len(batch) == 2 and batch.key == structure_key(batch.scenes[0])
    assert all(s.image.spp is not None for s in batch.scenes)  # at their quality level
    assert prepare.prepare(batch) is batch


def test_input_is_refused_before_anything_renders(monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("a render started before its input was checked")

    monkeypatch.setattr(executor, "RenderContext", no_render)
    with pytest.raises(ValueError, match=r"^image.passes: got 2; passes differ"):
        tv.render(box(passes=2, spp=1) | {"march": {"dither": "none"}})
    with pytest.raises(ValueError, match=r"scenes\[1\]\.volumes: got 2"):
        tv.render([box(), box() | {"volumes": [{"density": {"constant": 1.0}}] * 2}])
    with pytest.raises(ValueError, match=r"^aovs: got 'sun_visibility'; needs lights\[0\] to be a sun"):
        tv.render(box() | {"lights": [{"kind": "point", "position": [0, 2, 0]}]}, aovs=["sun_visibility"])


def test_render_takes_a_prepared_batch_without_preparing_it_again(monkeypatch):
    batch = prepare.prepare(box())
    calls = []
    monkeypatch.setattr(prepare, "at_level", lambda scene: calls.append(scene) or scene)
    monkeypatch.setattr(prepare, "check_same_structure", lambda scenes: calls.append(scenes))
    out = tv.render(batch)
    assert not calls and out.image.shape == (1, 3, 4, 6)
    monkeypatch.undo()
    assert tv.render(box()).image.equal(out.image)


def test_group_levels_each_scene_once_and_splits_by_structure(monkeypatch):
    scenes = [tv.load_scene(box()), tv.load_scene(box() | {"volumes": [{"density": {"constant": 1.0}}] * 2}),
              tv.load_scene(box())]
    levelled = []
    real = prepare.at_level
    monkeypatch.setattr(prepare, "at_level", lambda scene: levelled.append(scene) or real(scene))
    groups = prepare.group(scenes)
    assert len(levelled) == 3
    assert [positions for positions, _ in groups] == [[0, 2], [1]]
    assert [len(batch) for _, batch in groups] == [2, 1]


def test_volume_labels_come_from_the_render_context(monkeypatch):
    recipe = tv.Recipe.load({**box(), "dataset": {"volume_label": {"resolution": 4}},
                             "volumes": [{"bounds": {"box": {"min": [-1, -1, -1], "max": [1, 1, 1]}},
                                          "density": {"constant": {"uniform": [0.5, 2.0]}}}]})
    built = []
    real = executor.RenderContext.__init__

    def counted(self, *args, **kwargs):
        built.append(1)
        real(self, *args, **kwargs)

    monkeypatch.setattr(executor.RenderContext, "__init__", counted)
    items = tv.SceneDataset(recipe, length=3, compile="off").batch([0, 1, 2])
    assert len(built) == 1  # one batch, one context: the labels reuse it
    monkeypatch.setattr(executor.RenderContext, "__init__", real)
    from torchvol.dataset.volume_label import extinction_grid

    for k, item in enumerate(items):
        alone, box_alone = extinction_grid(recipe.sample(k, 0), 4)
        assert item["extinction"].equal(alone) and item["extinction_box"].equal(box_alone), k
