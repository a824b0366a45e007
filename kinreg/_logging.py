import logging

logging.getLogger("kinreg").addHandler(logging.NullHandler())
