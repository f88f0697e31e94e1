"""The renderer: a batch of scenes -> a plan -> passes run in ray chunks -> a RenderOutput."""
