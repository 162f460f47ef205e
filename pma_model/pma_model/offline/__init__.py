"""What runs offline, never in model_node: reading recordings (samples), the refit and its
report, data checks, figures (plots, bag_plot) and provenance. The online core (the model,
its learning, model_node) is the package above and imports nothing from here."""
