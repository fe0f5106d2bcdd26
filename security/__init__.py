"""The yard's security material, beside ``schemas`` in the layers (it imports only
``common``, the standard library and ``cryptography``).

- :mod:`security.pki`: the site PKI a yard runs itself: a site CA, a certificate per
  service (its role recorded in the certificate), revocation (a CRL signed by the CA and
  an index), reading certificates back and warning before one expires
- :mod:`security.cli`: ``stockpile pki init | issue | revoke | list``
"""
