"""The event simulator's implementation, one concern per module; use it through :mod:`evlatcorr.simulate`.

- ``photographs``: source images (bundled photographs, user images) and luminance;
- ``motion``: camera trajectories and the moving view of a photograph;
- ``objects``: :class:`~evlatcorr.simulate.ObjectSpec` sprites moving over a still background;
- ``generator``: contrast thresholds and threshold crossings of the log intensity;
- ``latency``: the latency models and the photoreceptor filter;
- ``noise``: shot noise, leak events and the refractory period;
- ``settings``: checking :func:`~evlatcorr.simulate.simulate`'s arguments;
- ``timeline``: exposures, time step, warm-up and target times;
- ``stepping``: the time-stepping loop (exposures, photoreceptor, event generators);
- ``sequence``: :class:`~evlatcorr.simulate.SimulatedSequence`;
- ``simulator``: :func:`~evlatcorr.simulate.simulate` itself.
"""
