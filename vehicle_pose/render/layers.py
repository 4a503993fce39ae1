"""Many poses in one draw: each instance of the mesh into its own layer of layered targets.

A search that scores a population (the cross-entropy method's generations, CMA-ES's) has its
poses before it scores any, so they can be drawn together: one instanced draw call, the vertex
shader sending instance ``i`` to layer ``i`` (``gl_Layer``) with its own matrices, into layered
attribute, label and depth textures; each pose's window is then read back from its layer.
Every layer has the whole image's size and the same viewport as a single draw, so a pose's
frame is the single draw's bit for bit (the tests check it). On llvmpipe this saves part of
each frame's fixed cost, 9-22 % of a pose at 160-640 pixels in draws of 100 (`bench/throughput.py`);
on a GPU, where a frame's work is microseconds and each draw's synchronisation is the cost, it
should save far more (not measured: no GPU lent since the batches were built).

Only the layers a draw uses are cleared (``glClearTexSubImage``, within the draw's window): a
clear of the framebuffer clears every layer, and on llvmpipe clearing a 100-layer target for a
generation of 9 poses cost more than drawing them one at a time (1.5 ms a pose at 320x240
against 0.5-0.8 ms).

It needs a vertex shader that may set the layer (``GL_ARB_shader_viewport_layer_array`` or
``GL_AMD_vertex_shader_layer``), ``glGetTextureSubImage`` (OpenGL 4.5 or
``GL_ARB_get_texture_sub_image``) and ``glClearTexSubImage`` (OpenGL 4.4 or
``GL_ARB_clear_texture``), called through ctypes; :func:`supported` says whether the context
has them, and the renderer draws one pose at a time where it does not.
"""

from __future__ import annotations

import ctypes
import functools
from typing import Any

import moderngl
import numpy as np

from vehicle_pose.errors import RenderError
from vehicle_pose.render.gl import gl_library

__all__ = ["LAYER_EXTENSIONS", "MAX_LAYERS", "LayeredTarget", "supported"]

LAYER_EXTENSIONS = ("GL_ARB_shader_viewport_layer_array", "GL_AMD_vertex_shader_layer")
"""Extensions that let a vertex shader choose the layer it draws to."""

MAX_LAYERS = 100
"""Poses a draw at most (a cross-entropy generation): the vertex shader's matrices for them are
2 x 100 mat4 uniforms, 3200 components (llvmpipe offers 16384, NVIDIA 4096; a driver with fewer
fails to link the program and the renderer draws one pose at a time). On llvmpipe a pose drawn
among 100 costs 9-22 % less than alone, among 32 2-14 % less (`bench/throughput.py`)."""

_BYTES = 16 + 1 + 4  # a pixel of a layer: attributes (RGBA float32), label (R8), depth (24-bit, padded)

_TEXTURE_2D_ARRAY, _RGBA32F, _R8, _DEPTH24 = 0x8C1A, 0x8814, 0x8229, 0x81A6
_FRAMEBUFFER, _COLOR0, _DEPTH_ATTACHMENT, _FRAMEBUFFER_COMPLETE = 0x8D40, 0x8CE0, 0x8D00, 0x8CD5
_RGBA, _RED, _FLOAT, _UNSIGNED_BYTE, _PACK_ALIGNMENT = 0x1908, 0x1903, 0x1406, 0x1401, 0x0D05
_DEPTH_COMPONENT = 0x1902


class _Calls:
    """The OpenGL calls moderngl does not make: layered textures and reading one layer's window."""

    glGenTextures: Any
    glDeleteTextures: Any
    glBindTexture: Any
    glTexStorage3D: Any
    glGenFramebuffers: Any
    glDeleteFramebuffers: Any
    glBindFramebuffer: Any
    glFramebufferTexture: Any
    glDrawBuffers: Any
    glGetTextureSubImage: Any
    glClearTexSubImage: Any
    glPixelStorei: Any
    glCheckFramebufferStatus: Any

    def __init__(self, lib: ctypes.CDLL) -> None:
        uint, int_, ptr = ctypes.c_uint, ctypes.c_int, ctypes.c_void_p
        signatures = {
            "glGenTextures": [int_, ptr],
            "glDeleteTextures": [int_, ptr],
            "glBindTexture": [uint, uint],
            "glTexStorage3D": [uint, int_, uint, int_, int_, int_],
            "glGenFramebuffers": [int_, ptr],
            "glDeleteFramebuffers": [int_, ptr],
            "glBindFramebuffer": [uint, uint],
            "glFramebufferTexture": [uint, uint, uint, int_],
            "glDrawBuffers": [int_, ptr],
            "glGetTextureSubImage": [uint, int_, int_, int_, int_, int_, int_, int_, uint, uint, int_, ptr],
            "glClearTexSubImage": [uint, int_, int_, int_, int_, int_, int_, int_, uint, uint, ptr],
            "glPixelStorei": [uint, int_],
        }
        for name, args in signatures.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = args, None
            setattr(self, name, fn)
        self.glCheckFramebufferStatus = lib.glCheckFramebufferStatus
        self.glCheckFramebufferStatus.argtypes, self.glCheckFramebufferStatus.restype = [uint], uint


@functools.cache
def _calls() -> _Calls | None:
    lib = gl_library()
    try:
        return None if lib is None else _Calls(lib)
    except AttributeError:  # a library without these entry points
        return None


def supported(ctx: moderngl.Context) -> bool:
    """Whether ``ctx`` can draw poses into layers, clear some of them and read one layer's
    window back."""
    extensions = ctx.extensions
    readable = ctx.version_code >= 450 or "GL_ARB_get_texture_sub_image" in extensions
    clearable = ctx.version_code >= 440 or "GL_ARB_clear_texture" in extensions
    return (readable and clearable and any(e in extensions for e in LAYER_EXTENSIONS)
            and _calls() is not None)


class LayeredTarget:
    """Layered attribute (RGBA float32), label (R8) and depth textures of ``width`` x ``height``
    x ``layers``, and the framebuffer that draws into them, wrapped for moderngl."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, layers: int) -> None:
        calls = _calls()
        if calls is None:
            raise RenderError("no OpenGL library to make layered targets with")
        self.calls, self.width, self.height, self.layers = calls, width, height, layers
        self.textures = (ctypes.c_uint * 3)()
        calls.glGenTextures(3, self.textures)
        for texture, kind in zip(self.textures, (_RGBA32F, _R8, _DEPTH24), strict=True):
            calls.glBindTexture(_TEXTURE_2D_ARRAY, texture)
            calls.glTexStorage3D(_TEXTURE_2D_ARRAY, 1, kind, width, height, layers)
        calls.glBindTexture(_TEXTURE_2D_ARRAY, 0)
        self.framebuffer_id = ctypes.c_uint()
        calls.glGenFramebuffers(1, ctypes.byref(self.framebuffer_id))
        calls.glBindFramebuffer(_FRAMEBUFFER, self.framebuffer_id)
        calls.glFramebufferTexture(_FRAMEBUFFER, _COLOR0, self.textures[0], 0)
        calls.glFramebufferTexture(_FRAMEBUFFER, _COLOR0 + 1, self.textures[1], 0)
        calls.glFramebufferTexture(_FRAMEBUFFER, _DEPTH_ATTACHMENT, self.textures[2], 0)
        calls.glDrawBuffers(2, (ctypes.c_uint * 2)(_COLOR0, _COLOR0 + 1))
        complete = calls.glCheckFramebufferStatus(_FRAMEBUFFER) == _FRAMEBUFFER_COMPLETE
        self.fbo = ctx.detect_framebuffer(self.framebuffer_id.value)
        # moderngl's detection asks for the attachments' renderbuffer sizes, which textures do
        # not have, and records GL_INVALID_OPERATION: taken off here, the framebuffer is whole.
        _ = ctx.error
        if not complete:
            self.release()
            raise RenderError("the layered framebuffer is incomplete")
        # Each draw clears its own layers with glClearTexSubImage: a driver that will not (an
        # error recorded) is found here, by a clear of one pixel, where the renderer can still
        # draw one pose at a time, rather than at a search's first generation.
        self.clear(1, (0, 0, 1, 1))
        error = ctx.error
        if error != "GL_NO_ERROR":
            self.release()
            raise RenderError(f"the layered target cannot be cleared ({error})")

    @staticmethod
    def nbytes(width: int, height: int, layers: int) -> int:
        """Memory of a target of that size."""
        return width * height * layers * _BYTES

    def clear(self, layers: int, window: tuple[int, int, int, int]) -> None:
        """Clear the labels (to 0) and the depth (to 1) of ``window`` (x0, y0, w, h) in the first
        ``layers`` layers: what a draw into them needs, as a framebuffer clear gives it."""
        x0, y0, w, h = window
        self.calls.glClearTexSubImage(self.textures[1], 0, x0, y0, 0, w, h, layers, _RED, _UNSIGNED_BYTE,
                                      ctypes.byref(ctypes.c_uint8(0)))
        self.calls.glClearTexSubImage(self.textures[2], 0, x0, y0, 0, w, h, layers, _DEPTH_COMPONENT, _FLOAT,
                                      ctypes.byref(ctypes.c_float(1.0)))

    def read(self, layer: int, window: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The attributes (h, w, 4) and labels (h, w) of ``window`` (x0, y0, w, h) of ``layer``."""
        x0, y0, w, h = window
        attrs = np.empty((h, w, 4), np.float32)
        labels = np.empty((h, w), np.uint8)
        # Rows packed without padding (moderngl's reads leave this set, but not every context
        # has read through moderngl first).
        self.calls.glPixelStorei(_PACK_ALIGNMENT, 1)
        self.calls.glGetTextureSubImage(self.textures[0], 0, x0, y0, layer, w, h, 1, _RGBA, _FLOAT, attrs.nbytes,
                                        attrs.ctypes.data)
        self.calls.glGetTextureSubImage(self.textures[1], 0, x0, y0, layer, w, h, 1, _RED, _UNSIGNED_BYTE,
                                        labels.nbytes, labels.ctypes.data)
        return attrs, labels

    def release(self) -> None:
        """Free the textures and the framebuffer (the caller binds another framebuffer first:
        moderngl rebinds the one bound last whenever it makes one)."""
        self.calls.glDeleteFramebuffers(1, ctypes.byref(self.framebuffer_id))
        self.calls.glDeleteTextures(3, self.textures)
