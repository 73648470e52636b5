"""C-SAM's join: the local maps' consistency check, rendezvous filters, alignment (Algorithm 1),
association, the joint solve and its typed result. Imports the layers below."""
