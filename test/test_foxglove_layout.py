"""config/foxglove/uav_vs.json, the layout that ships: a layout both Foxglove and
Lichtblick import (the classic `configById` + `layout` form). That it names only topics
and fields the graph publishes is checked against a flight: test_closed_loop's PX4 flight
runs the live view and compares the layout with the channels foxglove_node advertised."""
import pytest

from uav_vs.flight.live_view import SLOW_LINK, load_layout, panels, references


def test_every_panel_of_the_tree_is_configured_and_every_configured_one_shown():
    layout = load_layout()
    shown = panels(layout['layout'])
    assert len(shown) == len(set(shown))
    assert set(shown) == set(layout['configById'])
    for key in ('globalVariables', 'userNodes', 'playbackConfig'):
        assert key in layout


def test_the_layout_shows_what_an_operator_watches():
    refs = {topic for _, topic, _ in references(load_layout())}
    for cam in ('cam1', 'cam2', 'cam3'):
        assert {f'/{cam}/image_raw/compressed', f'/{cam}/landmark_windows'} <= refs
    assert {'/onboard/image_raw/compressed', '/onboard/target_outline', '/cmd_vel', '/setpoint',
            '/diagnostics'} <= refs
    for source in ('ground', 'onboard', 'fused', 'truth'):
        assert f'/{source}/pose' in refs


def test_the_windows_are_drawn_on_the_frame_they_were_found_in():
    """The app's "Sync annotations" shows a ground camera's frame with the landmark windows
    of the same stamp (camshift_node publishes them for every frame while watched), not the
    newest windows over an older frame. The onboard outline comes only while following a
    target: synchronised, the onboard panel would wait for it and show no frame."""
    config = load_layout()['configById']
    for cam in ('cam1', 'cam2', 'cam3'):
        assert config[f'Image!{cam}']['imageMode']['synchronize'] is True
    assert not config['Image!onboard']['imageMode'].get('synchronize', False)


def test_the_plots_show_the_whole_flight_live_and_in_a_bag():
    """No following window: a plot that follows the newest seconds works live, but
    Lichtblick leaves it empty when it plays a recorded bag."""
    plots = [c for k, c in load_layout()['configById'].items() if k.startswith('Plot!')]
    assert len(plots) == 4
    assert all('followingViewWidth' not in c and c['xAxisVal'] == 'timestamp' for c in plots)


def test_references_name_each_panels_topics_and_plot_fields():
    layout = {'configById': {
        'Image!a': {'imageMode': {'imageTopic': '/c/image', 'calibrationTopic': '',
                                  'annotations': {'/c/marks': {'visible': True}}}},
        '3D!b': {'topics': {'/p': {'visible': True}, '/hidden': {'visible': False}}},
        'Plot!c': {'paths': [{'value': '/p.pose.position.x'}]},
        'DiagnosticSummary!d': {'topicToRender': '/diagnostics'}}}
    assert sorted(references(layout)) == sorted([
        ('Image!a', '/tf', ()), ('Image!a', '/tf_static', ()), ('Image!a', '/c/image', ()),
        ('Image!a', '/c/marks', ()), ('3D!b', '/tf', ()), ('3D!b', '/tf_static', ()),
        ('3D!b', '/p', ()), ('Plot!c', '/p', ('pose', 'position', 'x')),
        ('DiagnosticSummary!d', '/diagnostics', ())])
    with pytest.raises(ValueError, match='Gauge!e'):
        references({'configById': {'Gauge!e': {}}})


def test_the_slow_link_layout_is_the_layout_on_the_smaller_frames():
    """uav_vs_slow_link.json: the same panels, the images and their annotations the
    `/jpeg` copies config/foxglove_slow_link.yaml has foxglove_node serve, without the
    full-size calibration (3D view and plots unchanged)."""
    expected = load_layout()
    for panel, config in expected['configById'].items():
        if panel.startswith('Image!'):
            mode = config['imageMode']
            mode['imageTopic'] += '/jpeg'
            del mode['calibrationTopic']
            mode['annotations'] = {f'{t}/jpeg': v for t, v in mode['annotations'].items()}
    assert load_layout(SLOW_LINK) == expected
