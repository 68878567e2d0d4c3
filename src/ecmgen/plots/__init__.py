"""The plots: :mod:`ecmgen.plots.style` (the house style and the headless pyplot, shared by
every stage that draws) and :mod:`ecmgen.plots.figures` (a build's PNGs). Empty on purpose:
a stage that needs only the style does not load the build's figures."""
