"""Pure-torch cores of the agent package (no ROS imports).

- :mod:`.config`     hyper-parameters (frozen dataclasses, one default per parameter, thesis value beside it)
- :mod:`.qt`         the Q-target network QT (LSTM), its scaler, array (de)serialisation, reduction predictor
- :mod:`.networks`   DDPG actor / critic (Appendix B), Nature-DQN CNN (Table 36), torch runtime set-up
- :mod:`.noise`      Ornstein-Uhlenbeck exploration noise (numpy)
- :mod:`.replay`     plain uniform FIFO replay buffer (DDPG / DQN baselines)
- :mod:`.comcact`    COMCACT / DDPG learner (Algorithm 8)
- :mod:`.comper`     COMPER / COMPER-F / COMPER-M / DQN learner (Algorithm 7), DQN-style RMSProp
- :mod:`.checkpoint` atomic torch.save of plain state dicts, loadable with weights_only=True

Submodules are imported lazily so that ``config`` can be used without importing torch.
"""
