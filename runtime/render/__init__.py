"""Drawing the shaded object into the frame: GL context, meshes and shaders, the compositor passes,
the cast shadow, and the :class:`~illuminet.runtime.render.stage.RenderStage` that ties them together.
"""
