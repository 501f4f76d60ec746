"""What the demo's figures say and how they use their space (evaluation.plots): the
trajectory marks errors above the alert limit (it marked a fixed 10 m), a wide track fills
its panels (side by side, the smartLoc track left most of each panel blank), the risk
legend sits beside the curves (it covered them), titles are readable, and the risk figure
names its reference risk."""
import numpy as np
import pytest

from gnsscam_ros.evaluation import plots


@pytest.fixture
def figures(monkeypatch):
    """The figures the plot functions make, kept open instead of saved."""
    made = []

    def keep(fig, path):
        fig.canvas.draw()
        made.append(fig)
        return path
    monkeypatch.setattr(plots, '_save', keep)
    yield made
    for fig in made:
        plots.plt.close(fig)


def wide_track(n=400, length_m=2000.0, height_m=150.0):
    t = np.linspace(0.0, 1.0, n)
    truth = np.c_[t * length_m, height_m * np.sin(6 * t), np.zeros(n)]
    rng = np.random.default_rng(0)
    return truth, truth + np.c_[rng.normal(0, 6.0, (n, 2)), np.zeros(n)]


def test_trajectory_marks_the_alert_limit_and_fills_its_panels(figures):
    truth, est = wide_track()
    plots.trajectory_plot('t.png', 'T', truth, {'nodes': est, 'offline': est}, 16.0)
    (fig,) = figures
    axes = fig.axes
    err = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    labels = [t.get_text() for t in axes[0].get_legend().get_texts()]
    assert f'error > alert limit 16 m ({np.mean(err > 16.0):.0%})' in labels
    for ax in axes:
        x0, x1 = ax.get_xlim()
        y0, y1 = ax.get_ylim()
        # The track spans most of the panel along its long side, and the panel is not
        # mostly empty across it either.
        assert np.ptp(truth[:, 0]) / (x1 - x0) > 0.8
        assert np.ptp(truth[:, 1]) / (y1 - y0) > 0.4
    # A wide track: panels stacked, one above the other.
    assert axes[0].get_position().y0 > axes[1].get_position().y1


def test_risk_legend_is_beside_the_curves_and_names_the_reference(figures):
    t = np.arange(100.0)
    bound, reference = np.full(100, 0.3), np.linspace(0.0, 1.0, 100)
    plots.risk_plot('r.png', 'R', t, bound, reference, 8.0, 0.1,
                    reference_label='reference risk: offline M posteriors')
    (fig,) = figures
    (ax,) = fig.axes
    legend = ax.get_legend()
    renderer = fig.canvas.get_renderer()
    assert legend.get_window_extent(renderer).x0 >= ax.get_window_extent(renderer).x1
    texts = [x.get_text() for x in legend.get_texts()]
    assert 'reference risk: offline M posteriors' in texts
    assert f'bound < reference: failure ratio {np.mean(bound < reference):.0%}' in texts


@pytest.mark.parametrize('name, title', [
    ('emulated-urban-s3-f6', 'Emulated urban drive (seed 3, 6 faulty satellites)'),
    ('emulated-urban-s2-f1-nonlos', 'Emulated urban drive (seed 2, 1 faulty satellite, '
                                    'no NLOS)'),
    ('emulated-urban-s1-f0', 'Emulated urban drive (seed 1, no faulty satellite)'),
    ('Berlin_Potsdamer_Platz', 'smartLoc Berlin Potsdamer Platz'),
    ('my_drive', 'my_drive'),
])
def test_dataset_titles_are_readable(name, title):
    assert plots.dataset_title(name) == title
