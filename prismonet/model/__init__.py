"""The PriSMONet scene model: recurrent object encoder, background encoder, texture field, and
the frozen shape prior, decoded by the differentiable renderer."""
