"""Neural-network pieces: VGG19 features (`vgg`) and the style / content losses (`losses`)."""

from wrinkle_jax.nn.vgg import VGGSpec, features, init_vgg19, load_vgg19

__all__ = ["VGGSpec", "features", "init_vgg19", "load_vgg19"]
