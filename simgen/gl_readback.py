"""pyrender's offscreen framebuffers made exact and cheap: single-sample buffers, read back
directly, on EGL and on OSMesa alike.

pyrender has no option for any of these, so :class:`simgen.camera.Renderer` patches its module
function and its platform instance (its framebuffers and its EGL display's lifetime) and stands
these readers in for its instance's ``_read_main_framebuffer``.
"""
from __future__ import annotations

import collections
import ctypes

import numpy as np

_EGL_DISPLAY_USERS: collections.Counter = collections.Counter()


def single_sample_framebuffers(renderer_module) -> None:
    """Make pyrender's offscreen framebuffers single-sample.

    pyrender renders into a 4x multisample framebuffer and resolves it with GL_LINEAR, which
    averages the id colours of the segmentation pass at every object edge into ids of other
    objects; the id pass must be exact. It is also most of the cost on a software rasteriser.
    Samples = 0 asks GL for an ordinary renderbuffer, so the resolve becomes a plain copy.
    """
    original = renderer_module.glRenderbufferStorageMultisample
    if getattr(original, "_simgen_single_sample", False):
        return

    def storage(target, samples, internal_format, width, height):
        return original(target, 0, internal_format, width, height)

    storage._simgen_single_sample = True
    renderer_module.glRenderbufferStorageMultisample = storage


def framebuffers_on_osmesa(offscreen) -> None:
    """Let pyrender's ``OffscreenRenderer`` render into framebuffer objects on OSMesa too, as it
    does on EGL, so that one set of readers (below) serves both platforms.

    pyrender's OSMesa platform says it has no framebuffer objects, so pyrender renders into
    OSMesa's window buffer and reads it with ``read_color_buf``, which asks GL for RGB whatever
    the render flags say: the id pass got (H, W, 3) bytes, which cannot be viewed as one uint32
    face index per pixel, and the sun's orthographic depth came back linearised as a perspective
    one. Yet the context pyrender creates on OSMesa is an OpenGL 3.3 core profile (its shaders
    need it), and framebuffer objects are core since OpenGL 3.0. On the same Mesa rasteriser the
    two platforms then give the same bytes (rgb, depth and ids; tests/simgen/test_osmesa.py).
    ``offscreen``: a ``pyrender.OffscreenRenderer``; EGL's platform is left as it is.
    """
    platform = offscreen._platform
    if not platform.supports_framebuffers():
        platform.supports_framebuffers = lambda: True


def share_egl_display(offscreen) -> None:
    """Let several pyrender ``OffscreenRenderer`` objects live in one process on EGL.

    EGL hands every renderer of a device the same display, and pyrender's ``delete_context``
    terminates it, which invalidates every other renderer's context: the next one to make its
    context current fails with EGL_BAD_DISPLAY (a renderer closed, or collected, while another
    lives). Here the display is terminated only when its last renderer goes. ``offscreen``: a
    ``pyrender.OffscreenRenderer``; other platforms are left as they are.
    """
    platform = offscreen._platform
    display = getattr(platform, "_egl_display", None)
    if display is None:
        return
    key = ctypes.cast(display, ctypes.c_void_p).value
    _EGL_DISPLAY_USERS[key] += 1

    def delete_context():
        from OpenGL.EGL import eglDestroyContext, eglTerminate
        if platform._egl_display is None:
            return
        if platform._egl_context is not None:
            eglDestroyContext(platform._egl_display, platform._egl_context)
            platform._egl_context = None
        _EGL_DISPLAY_USERS[key] -= 1
        if _EGL_DISPLAY_USERS[key] == 0:
            del _EGL_DISPLAY_USERS[key]
            eglTerminate(platform._egl_display)
        platform._egl_display = None

    platform.delete_context = delete_context


def read_single_sample_framebuffer(renderer, scene, flags, with_depth: bool = True):
    """Stands in for pyrender's ``Renderer._read_main_framebuffer``, given single-sample
    buffers: read the render target directly, without pyrender's blit into a second framebuffer,
    and linearise depth with whole-array float32 arithmetic instead of boolean-mask indexing.

    Returns rgba (H, W, 4) uint8 and depth (H, W) float32 camera z (m), 0 where nothing was hit,
    both top row first, as pyrender's reader does; depth is None unless ``with_depth``.
    """
    from OpenGL.GL import (GL_DEPTH_COMPONENT, GL_FLOAT, GL_READ_FRAMEBUFFER, GL_RGBA, GL_UNSIGNED_BYTE,
                           glBindFramebuffer, glReadPixels)
    w, h = renderer._main_fb_dims
    glBindFramebuffer(GL_READ_FRAMEBUFFER, renderer._main_fb_ms)
    rgba = np.frombuffer(glReadPixels(0, 0, w, h, GL_RGBA, GL_UNSIGNED_BYTE), np.uint8).reshape(h, w, 4)[::-1]
    if not with_depth:
        return rgba, None
    ndc = np.frombuffer(glReadPixels(0, 0, w, h, GL_DEPTH_COMPONENT, GL_FLOAT), np.float32).reshape(h, w)[::-1]
    cam = scene.main_camera_node.camera
    n, f = cam.znear, cam.zfar
    depth = (2.0 * n * f) / (f + n - (2.0 * ndc - 1.0) * (f - n))      # float32, as pyrender computes it
    depth[ndc == 1.0] = 0.0
    return rgba, depth


def read_window_depth(renderer, scene, flags):
    """Stands in for ``Renderer._read_main_framebuffer`` in the shadow pass: the depth
    buffer as it is, (H, W) float32 window depth in [0, 1] (1 = nothing), top row first. The
    shadow camera is orthographic, so window depth is already linear in distance."""
    from OpenGL.GL import GL_DEPTH_COMPONENT, GL_FLOAT, GL_READ_FRAMEBUFFER, glBindFramebuffer, glReadPixels
    w, h = renderer._main_fb_dims
    glBindFramebuffer(GL_READ_FRAMEBUFFER, renderer._main_fb_ms)
    return np.frombuffer(glReadPixels(0, 0, w, h, GL_DEPTH_COMPONENT, GL_FLOAT), np.float32).reshape(h, w)[::-1]
