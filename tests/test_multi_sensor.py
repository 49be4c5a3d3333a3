"""Several sensors in one scene: `scene.sensors`, `render(scene, sensor=k)` as Mitsuba's
`mi.render(scene, sensor=k)`, and one loss over the images of several sensors."""
import copy
import pickle

import pytest
import torch

import torch_rbpt as tr

KEY = "red.reflectance.value"
TRUE_RED = [0.7, 0.15, 0.1]


def _sensors():
    """A perspective view from the front and an orthographic view from above, with films of
    different sizes and filters."""
    front = {"type": "perspective", "fov": 50,
             "to_world": tr.Transform.look_at([0, -4, 1.5], [0, 0, 0.5], [0, 0, 1]),
             "film": {"type": "hdrfilm", "width": 12, "height": 9}}
    top = {"type": "orthographic",
           "to_world": tr.Transform.look_at([0.3, 0.2, 5], [0.3, 0.2, 0], [0, 1, 0]) @ tr.Transform.scale([1.6, 1.6, 1]),
           "film": {"type": "hdrfilm", "width": 10, "height": 10, "rfilter": {"type": "box"}}}
    return front, top


def _scene_dict(sensors, red=TRUE_RED):
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": 3},
         "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": red}},
         "floor": {"type": "rectangle", "bsdf": {"type": "ref", "id": "red"},
                   "to_world": tr.Transform.scale([2, 2, 1])},
         "ball": {"type": "sphere", "center": [0.4, 0.3, 0.5], "radius": 0.5,
                  "bsdf": {"type": "diffuse"}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}
    for i, s in enumerate(sensors):
        d[f"sensor_{i}"] = s
    return d


def test01_each_sensor_renders_as_if_it_were_the_only_one():
    front, top = _sensors()
    scene = tr.load_dict(_scene_dict([front, top]))
    assert len(scene.sensors) == 2 and scene.sensor is scene.sensors[0]
    assert scene.sensors[1].film.width == 10
    images = [tr.render(scene, spp=4, seed=3, sensor=k) for k in (0, 1)]
    assert images[0].shape == (9, 12, 3) and images[1].shape == (10, 10, 3)
    for k, alone in enumerate((front, top)):
        single = tr.load_dict(_scene_dict([alone]))
        assert torch.equal(images[k], tr.render(single, spp=4, seed=3)), k
    # The default is the first sensor; a Sensor object and a negative index name one too.
    assert torch.equal(tr.render(scene, spp=4, seed=3), images[0])
    assert torch.equal(tr.render(scene, spp=4, seed=3, sensor=scene.sensors[1]), images[1])
    assert torch.equal(tr.render(scene, spp=4, seed=3, sensor=-1), images[1])
    # Each sensor keeps its own film: editing one leaves the other alone.
    scene.sensors[1].film.width = 6
    assert tr.render(scene, spp=1, sensor=1).shape == (10, 6, 3)
    assert tr.render(scene, spp=1, sensor=0).shape == (9, 12, 3)


def test02_a_bad_sensor_is_a_clear_error():
    scene = tr.load_dict(_scene_dict(list(_sensors())))
    other = tr.load_dict(_scene_dict(list(_sensors())))
    with pytest.raises(ValueError, match=r"sensor must be an index into the scene's 2 sensor\(s\)"):
        tr.render(scene, spp=1, sensor=2)
    with pytest.raises(ValueError, match="sensor must be an index"):
        tr.render(scene, spp=1, sensor="top")
    with pytest.raises(ValueError, match="not one of the scene's sensors"):
        tr.render(scene, spp=1, sensor=other.sensors[0])


def test03_xml_sensors_in_file_order(tmp_path):
    path = tmp_path / "two.xml"
    path.write_text('''<scene version="3.0.0">
    <sensor type="perspective" id="a"><film type="hdrfilm"><integer name="width" value="8"/>
        <integer name="height" value="6"/></film></sensor>
    <shape type="sphere"><transform name="to_world"><translate z="4"/></transform></shape>
    <emitter type="constant"/>
    <sensor type="orthographic" id="b"><film type="hdrfilm"><integer name="width" value="5"/>
        <integer name="height" value="4"/></film>
        <sampler type="stratified"><integer name="sample_count" value="9"/></sampler></sensor>
</scene>''')
    scene = tr.load_file(path)
    assert [s.type for s in scene.sensors] == ["perspective", "orthographic"]
    assert [s.spp for s in scene.sensors] == [4, 9]  # each sensor keeps its own sampler
    assert tr.render(scene, sensor=1).shape == (4, 5, 3)


def test04_gradients_of_one_loss_over_several_sensors_add_up():
    # d(loss_0 + loss_1)/dp from one backward pass equals the sum of the two gradients
    # taken separately (replayed seeds make both exact), and forward mode agrees per sensor.
    scene = tr.load_dict(_scene_dict(list(_sensors())), dtype=torch.float64)
    red = scene.params[KEY].requires_grad_()
    targets = [torch.rand(9, 12, 3, dtype=torch.float64), torch.rand(10, 10, 3, dtype=torch.float64)]

    def loss_of(k):
        image = tr.render(scene, spp=2, seed=7, seed_grad=7, sensor=k)
        return ((image - targets[k]) ** 2).sum()

    parts = [torch.autograd.grad(loss_of(k), red)[0] for k in (0, 1)]
    total = torch.autograd.grad(loss_of(0) + loss_of(1), red)[0]
    torch.testing.assert_close(total, parts[0] + parts[1], rtol=1e-12, atol=0)
    assert float(parts[1].abs().sum()) > 0 and not torch.allclose(parts[0], parts[1])
    tangent = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    for k in (0, 1):
        jvp = tr.render_forward(scene, {KEY: tangent}, spp=2, seed=7, sensor=k)
        # Against a central difference of the replayed images (float64).
        eps = 1e-4
        with torch.no_grad():
            red += eps * tangent
            plus = tr.render(scene, spp=2, seed=7, sensor=k)
            red -= 2 * eps * tangent
            minus = tr.render(scene, spp=2, seed=7, sensor=k)
            red += eps * tangent
        torch.testing.assert_close(jvp, (plus - minus) / (2 * eps), rtol=1e-6, atol=1e-9)
        assert float(jvp.abs().sum()) > 0


def test05_a_multi_view_fit_recovers_the_reflectance():
    # One scene, two sensors, one loss: Adam on the sum of both views' L2 losses recovers the
    # floor's reflectance from references rendered with the true value.
    scene = tr.load_dict(_scene_dict(list(_sensors())))
    with torch.no_grad():
        targets = [tr.render(scene, spp=64, seed=1000 + k, sensor=k) for k in (0, 1)]
    red = scene.params[KEY]
    with torch.no_grad():
        red.copy_(torch.tensor([0.1, 0.6, 0.6]))
    red.requires_grad_()
    opt = torch.optim.Adam([red], lr=0.05)
    for it in range(60):
        opt.zero_grad()
        loss = sum(((tr.render(scene, spp=4, seed=it, sensor=k) - targets[k]) ** 2).mean() for k in (0, 1))
        loss.backward()
        opt.step()
        with torch.no_grad():
            red.clamp_(0, 1)
    assert torch.allclose(red.detach(), torch.tensor(TRUE_RED), atol=0.05), red


def test06_multi_sensor_scenes_pickle():
    scene = tr.load_dict(_scene_dict(list(_sensors())))
    scene.sensors[1].film.width = 7
    for copied in (pickle.loads(pickle.dumps(scene)), copy.deepcopy(scene)):
        assert len(copied.sensors) == 2
        for k in (0, 1):
            assert torch.equal(tr.render(copied, spp=2, seed=1, sensor=k), tr.render(scene, spp=2, seed=1, sensor=k))
