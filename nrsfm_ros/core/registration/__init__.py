"""Point set registration."""
from .icp import METHODS, RegistrationResult, icp, register

__all__ = ['METHODS', 'RegistrationResult', 'icp', 'register']
