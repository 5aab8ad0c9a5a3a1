"""Stable-Baselines3 pieces for gaitscope's task: the LSTM features extractor over the folded
window, shaped to gaitscope's contract (docs: LSTM(37 -> 32) over the 16-step window, features
[h_T, current observation]). Used by the peer benchmark (bench/peers/) and the import-sb3
fixtures (tests/fixtures/make_sb3_fixtures.py)."""

from gaitscope_gym import CONTEXT_LEN


def lstm_extractor():
    """SB3 features extractor: LSTM(37 -> 32) over the folded window, features [h_T, obs]."""
    import torch
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    class LstmWindow(BaseFeaturesExtractor):
        def __init__(self, observation_space, entry=37, z_dim=32):
            obs_dim = observation_space.shape[0] - CONTEXT_LEN * entry
            super().__init__(observation_space, features_dim=z_dim + obs_dim)
            self.split = CONTEXT_LEN * entry
            self.entry = entry
            self.lstm = torch.nn.LSTM(entry, z_dim, batch_first=True)

        def forward(self, obs):
            window = obs[:, : self.split].reshape(-1, CONTEXT_LEN, self.entry)
            _, (h, _) = self.lstm(window)
            return torch.cat([h[-1], obs[:, self.split :]], dim=1)

    return LstmWindow
