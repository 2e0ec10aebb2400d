"""Drawing the shaded object into the frame.

``gl`` (the context, desktop GL or OpenGL ES, and the GLSL dialect), ``egl`` (the OpenGL ES context
through EGL), ``mesh`` (drawable meshes and their loading), ``shaders`` (GLSL sources and
colour-transfer tables), ``shadow`` (the cast and contact shadow), ``compositor`` (the GPU passes)
and ``stage`` (the :class:`~illuminet.runtime.render.stage.RenderStage` that ties them together).
"""
