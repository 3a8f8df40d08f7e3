"""UniRelight Studio core: the joint relighting model, its sampler, lighting and media I/O."""
